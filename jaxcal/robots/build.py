"""Builders that turn a table in one of the seeds' layouts into a `Robot`.

- `pry_robot`: seed 000 Table 6.1 layout (body vector x y z, PRY angles, joint kind).
- `mdh_robot`: seed 001 Table 1 layout (sigma, alpha, d, theta, r, beta, K) for frames 0..n+1.
- `mcpc_robot`: seed 004 Table 4.1 layout (a1 a2 a3 d1 d2 d3 predecessor closure type).

Default priorities follow seed 001 §4: 5 joint offsets and gains, 4 non-zero r/d, 3 alpha/theta
not a multiple of pi/2, 2 base/tool frame, 1 the rest.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin import conventions as cv
from jaxcal.kin.model import Body, Robot
from jaxcal.kin.pose import Pose


def _multiple_of_half_pi(x: float) -> bool:
    r = np.mod(x, np.pi / 2)
    return min(r, np.pi / 2 - r) < 1e-9


class _Table:
    """Accumulates named parameters while a robot is built."""

    def __init__(self):
        self.names, self.values, self.units, self.free, self.priority = [], [], [], [], []

    def add(self, name, value, unit, free=True, priority=1.0) -> int:
        self.names.append(name)
        self.values.append(float(value))
        self.units.append(unit)
        self.free.append(bool(free))
        self.priority.append(float(priority))
        return len(self.names) - 1


def _limits(n, q_min, q_max, default_min, default_max):
    lo = np.full(n, default_min, float) if q_min is None else np.asarray(q_min, float)
    hi = np.full(n, default_max, float) if q_max is None else np.asarray(q_max, float)
    return lo, hi


def pry_robot(name, base_vector, modules, home=None, q_min=None, q_max=None, joint_names=None) -> Robot:
    """Robot of six-parameter PRY modules (seed 000 §3.2).

    modules: sequence of (kind, (bx, by, bz), (pitch, roll, yaw)) with angles in radians and
    kind one of seed 000 Table 3.3 ("revolute", "prismatic", "cylindrical", "universal",
    "spherical") or "fixed". The base vector b0 is a constant of the structure.
    """
    t = _Table()
    bodies, jn, n_in = [], [], 0
    for i, (kind, b, pry) in enumerate(modules, start=1):
        if kind not in cv.PRY_KINDS:
            raise ValueError(f"module {i}: unknown joint kind {kind!r}; expected one of {sorted(cv.PRY_KINDS)}")
        rows = tuple(
            t.add(f"j{i}.{field}", v, "length" if k < 3 else "angle")
            for k, (field, v) in enumerate(zip(cv.PRY_ROW, list(b) + list(pry)))
        )
        k_in = cv.PRY_KINDS[kind]
        inputs = tuple(range(n_in, n_in + k_in))
        jn += [f"j{i}" if k_in == 1 else f"j{i}.{c}" for c in "zyx"[:k_in]] if k_in else []
        n_in += k_in
        bodies.append(Body(f"j{i}", "pry", kind, i - 2, rows, inputs))
    joint_names = tuple(joint_names) if joint_names is not None else tuple(jn)
    lo, hi = _limits(n_in, q_min, q_max, -np.pi, np.pi)
    home = np.zeros(n_in) if home is None else np.asarray(home, float)
    return Robot(
        name=name, bodies=tuple(bodies), names=tuple(t.names), nominal_np=np.array(t.values),
        units=tuple(t.units), free_mask=np.array(t.free), priority=np.array(t.priority),
        joint_names=joint_names, home_np=home, q_min=lo, q_max=hi, tip=len(bodies) - 1,
        base=Pose(jnp.eye(3), jnp.asarray(base_vector, dtype=jnp.float64)),
    )


def mdh_robot(name, frames, home=None, q_min=None, q_max=None, joint_names=None,
              coupling_joint=None, coupling_motor=None) -> Robot:
    """Robot in Khalil-Kleinfinger modified DH with Hayati beta (seed 001 Table 1 layout).

    frames: rows (sigma, alpha, d, theta, r, beta, K) for frames 0..n+1. Frame 0 contributes
    theta0 and r0 only (alpha0 = d0 = 0, no beta); sigma = 2 frames carry no joint and no gain.
    Parameter names: "j{frame}.{alpha|d|theta|r|beta}" and "j{frame}.K".
    """
    t = _Table()
    bodies, gains, n_in = [], [], 0
    last = len(frames) - 1
    for j, row in enumerate(frames):
        if len(row) != 7:
            raise ValueError(f"frame {j}: expected 7 fields (sigma alpha d theta r beta K), got {len(row)}")
        sigma, alpha, d, theta, r, beta, _k = row
        sigma = int(sigma)
        if sigma not in (0, 1, 2):
            raise ValueError(f"frame {j}: sigma must be 0, 1 or 2, got {sigma}")
        end = j == 0 or j == last
        values = {"alpha": alpha, "d": d, "theta": theta, "r": r, "beta": beta}
        idx = []
        for field in cv.MDH_ROW:
            if j == 0 and field in ("alpha", "d", "beta"):
                idx.append(-1)
                continue
            v = float(values[field])
            unit = "length" if field in ("d", "r") else "angle"
            is_offset = (sigma == 0 and field == "theta") or (sigma == 1 and field == "r")
            if is_offset:
                prio = 5
            elif unit == "length" and abs(v) > 1e-12:
                prio = 4
            elif unit == "angle" and field != "beta" and not _multiple_of_half_pi(v):
                prio = 3
            elif end:
                prio = 2
            else:
                prio = 1
            idx.append(t.add(f"j{j}.{field}", v, unit, priority=prio))
        inputs = (n_in,) if sigma in (0, 1) else ()
        n_in += len(inputs)
        bodies.append(Body(f"j{j}", "mdh", sigma, j - 1, tuple(idx), inputs))
    for j, row in enumerate(frames):
        if int(row[0]) in (0, 1):
            gains.append(t.add(f"j{j}.K", row[6], "gain", priority=5))
    joint_names = tuple(joint_names) if joint_names is not None else tuple(
        f"j{j}" for j, row in enumerate(frames) if int(row[0]) in (0, 1))
    lo, hi = _limits(n_in, q_min, q_max, -np.pi, np.pi)
    home = np.zeros(n_in) if home is None else np.asarray(home, float)
    return Robot(
        name=name, bodies=tuple(bodies), names=tuple(t.names), nominal_np=np.array(t.values),
        units=tuple(t.units), free_mask=np.array(t.free), priority=np.array(t.priority),
        joint_names=joint_names, home_np=home, q_min=lo, q_max=hi, tip=len(bodies) - 1,
        gains=tuple(gains),
        coupling_joint=None if coupling_joint is None else np.asarray(coupling_joint, float),
        coupling_motor=None if coupling_motor is None else np.asarray(coupling_motor, float),
    )


# Which MCPC row entries are parameters for each joint type (seed 004 eq 2.45):
# rotary (a1 a2 a3 d1 d2), prismatic (a1 a2 d3), closure/auxiliary frames all six.
MCPC_USED = {
    0: ("a1", "a2", "a3", "d1", "d2"),
    1: ("a1", "a2", "d3"),
    2: cv.MCPC_ROW,
    3: cv.MCPC_ROW,
}


def mcpc_robot(name, rows, actuated=None, home=None, q_min=None, q_max=None, joint_names=None,
               tip=None, closure=None, closure_start=None) -> Robot:
    """Robot from seed 004 Table 4.1 rows (a1 a2 a3 d1 d2 d3 predecessor closure type).

    Bodies are numbered 1..N as in the table; predecessor 0 is the base. Rotary (0) and
    prismatic (1) bodies take a joint input unless `actuated` lists which bodies are driven
    (the others are then free joints solved by closure). Entries a row leaves unused (eq 2.45)
    must be zero. With `actuated` given and a non-zero closure column, `closure` defaults to
    `jaxcal.closure.closure_from_rows(rows, actuated, closure_start)`.
    """
    t = _Table()
    bodies, n_in, jn = [], 0, []
    actuated = None if actuated is None else set(int(b) for b in actuated)
    for i, row in enumerate(rows, start=1):
        if len(row) != 9:
            raise ValueError(f"row {i}: expected 9 fields (a1 a2 a3 d1 d2 d3 predecessor closure type), got {len(row)}")
        vals = dict(zip(cv.MCPC_ROW, (float(x) for x in row[:6])))
        pred, clo, typ = int(row[6]), int(row[7]), int(row[8])
        if typ not in MCPC_USED:
            raise ValueError(f"row {i}: field 'type' must be 0, 1, 2 or 3, got {typ}")
        if not 0 <= pred < i:
            raise ValueError(f"row {i}: field 'predecessor' = {pred} must name an earlier row (0 = base)")
        used = MCPC_USED[typ if clo == 0 else 2] if typ in (0, 1) and clo != 0 else MCPC_USED[typ]
        idx = []
        for field in cv.MCPC_ROW:
            if field in used:
                unit = "angle" if field.startswith("a") else "length"
                idx.append(t.add(f"j{i}.{field}", vals[field], unit))
            else:
                if abs(vals[field]) > 0:
                    raise ValueError(f"row {i}: field '{field}' is unused for type {typ} and must be 0")
                idx.append(-1)
        drives = typ in (0, 1) and (actuated is None or i in actuated)
        inputs = (n_in,) if drives else ()
        if drives:
            jn.append(f"j{i}")
        n_in += len(inputs)
        bodies.append(Body(f"j{i}", "mcpc", typ, pred - 1, tuple(idx), inputs))
    joint_names = tuple(joint_names) if joint_names is not None else tuple(jn)
    lo, hi = _limits(n_in, q_min, q_max, -np.pi, np.pi)
    home = np.zeros(n_in) if home is None else np.asarray(home, float)
    if closure is None and actuated is not None and any(int(row[7]) for row in rows):
        from jaxcal.closure.table import closure_from_rows

        closure = closure_from_rows(rows, actuated, closure_start)
    return Robot(
        name=name, bodies=tuple(bodies), names=tuple(t.names), nominal_np=np.array(t.values),
        units=tuple(t.units), free_mask=np.array(t.free), priority=np.array(t.priority),
        joint_names=joint_names, home_np=home, q_min=lo, q_max=hi,
        tip=len(bodies) - 1 if tip is None else tip - 1, closure=closure,
    )
