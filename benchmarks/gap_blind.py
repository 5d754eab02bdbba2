"""Blind check of `jc.gap.diagnose` (issue 7): generate cases, diagnose them without the labels, score.

    python benchmarks/gap_blind.py --cases 40 --folder /tmp/gap_blind [--seed 0] [--robots mrr1,stanford]
    python benchmarks/gap_blind.py --robots delta --cases 40 --folder /tmp/gap_blind_delta --max-steps 40 \
        --out benchmarks/results/gap_blind_delta

1. generate: each case draws a robot (from --robots: the built-in serial robots and the Delta), a
   device, a noise level, 30-300 samples, covariates, and a hidden truth: no effect, one library
   effect at a random separable joint with magnitude 1x-10x the noise RMS, or a decoy outside the
   library (third-harmonic joint error, a local bump over the workspace, a quadratic cross-joint
   error; right answer "unexplained"). Serial effects are then shrunk, where needed, so that no parameter leaves
   half of the diagnosis' sane box (`physical`: a gravity sag of tenths of a radian is no robot); the label's
   magnitude is the size after that. Data go to cases/NNN.npz; labels to labels.json, written apart.
   Delta (closed loop, position device, actuator settings reaching a 400 mm cube): its Table 4.6
   geometry absorbs the smooth actuator-space effects almost entirely (see `visible_fraction`), so
   effects are drawn among those whose displacement keeps >= VISIBLE_MIN of its size after the
   linearised geometry fit; an "absorbed" kind injects one of the others (right answer "none": after
   calibration nothing is left), and decoys are scaled on their visible part.
2. diagnose: reads only the case files (npz, and the CSV files of wide cases), writes predictions.json (or each
   shard's predictions_*.json, merged by the scorer).
3. score: reads labels and predictions; confusion matrix, top-1 accuracy, right-joint rate,
   false-alarm rate, mean shrink; results/gap_blind.json and a markdown table.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal import compiled  # noqa: E402
from jaxcal.gap.diagnose import box_limits, shrink_fraction  # noqa: E402
from jaxcal.gap.effects import GLOBAL_EFFECTS, JOINT_EFFECTS, NEEDS, gap_model  # noqa: E402
from jaxcal.gap.fit import covariate_matrix, jacobians, loads_and_tips, moment_norms, padded_size  # noqa: E402
from jaxcal.gap.simulate import add_noise, effect_vector, readings  # noqa: E402

ROBOTS = ("mrr1", "stanford")
# --wide without --robots: serial arms, the two-arm tree read at both hands, and the Delta (closed loop)
WIDE_MIX = {"mrr1": 0.38, "stanford": 0.47, "twoarm": 0.1, "delta": 0.05}  # a Delta diagnosis takes ~5 min
UNITS_MISTAKES = ("mm_as_m_csv", "mm_as_m_array", "deg_as_rad_csv")  # how a user gets the units wrong
DECOYS = ("harmonic3", "bump", "quadratic")
MAX_MAPPED_REGIONS = 30_000  # memory mappings past which compiled code is dropped (tests/conftest.py does the same)
VISIBLE_MIN = 0.2  # closed loops: share of an effect's displacement left after the linearised geometry fit
PHYSICAL_SHARE = 0.5  # serial draws: every effect parameter within this share of the diagnosis' sane box (`physical`)


def configurations(robot, n, seed):
    """Joint readings of n random samples: within the joint limits (serial), reaching the 400 mm cube (Delta)."""
    if robot.closure is not None:
        from jaxcal.gap.closed import delta_workspace

        if robot.name != "delta":
            raise ValueError(f"closed-loop robot {robot.name!r}: the blind benchmark draws workspaces for the Delta only")
        return delta_workspace(n, seed=seed)
    return jc.random_configurations(robot, n, seed=seed)


def geometry_basis(robot, model, x, q, cov):
    """Orthonormal basis (N*3, r) of the position-reading changes the geometry and device frame can make,
    linearised at x (base set with the calibration core's pivot tolerance), and the effect Jacobian
    columns (N*3, n_effect_params)."""
    from jaxcal.fit.base import base_set
    from jaxcal.fit.core import BASE_TOL

    n = len(q)
    C, _ = covariate_matrix(model, cov, n)
    npad = padded_size(n)
    qp = np.tile(robot.home_np, (npad, 1))
    qp[:n] = q
    Cp = np.zeros((npad, C.shape[1]))
    Cp[:n] = C
    w = np.zeros((npad, 3))
    w[:n] = 1.0
    _, J = jacobians(x[None], qp, np.zeros((npad, 3)), Cp, w, model=model)
    J = np.asarray(J[0])[: 3 * n]
    geo = np.flatnonzero(np.concatenate([robot.free_mask, model.device.free_mask]))
    prio = np.concatenate([robot.priority, model.device.priority])
    G = geo[base_set(J[:, geo], prio[geo], c=BASE_TOL / np.finfo(float).eps).independent]
    U, s, _ = np.linalg.svd(J[:, G], full_matrices=False)
    return U[:, s > 1e-10 * s[0]], J[:, model.n_geometry:]


def visible_fraction(basis, disp):
    """Share of a displacement (N, 3) the geometry cannot absorb: |(I - U U^T) d| / |d|."""
    d = np.asarray(disp).reshape(-1)
    return float(np.linalg.norm(d - basis @ (basis.T @ d)) / max(np.linalg.norm(d), 1e-300))


def _write_json(path, obj):
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(path)), suffix=".json")
    with os.fdopen(fd, "w") as fh:
        json.dump(obj, fh, indent=1)
    os.replace(tmp, path)


def separable_joints(robot, model, effect):
    """Joints where an effect acts on the readings and the geometry cannot absorb it exactly."""
    js = list(model.joints_with(effect))
    if effect == "encoder_gain" and robot.gains is not None:
        return []  # the transmission gains K are geometric parameters: a gain error is absorbed
    if effect == "compliance":
        q = jc.random_configurations(robot, 50, seed=1)
        loads, _ = loads_and_tips(model.nominal(), q, np.zeros((50, 2 + robot.n_inputs)), model=model)
        js = [j for j in js if np.std(np.asarray(loads)[:, j]) > 1e-3]
    if effect == "payload":  # no torque about a vertical axis: keep the joints where a unit constant moves the tip
        q = jc.random_configurations(robot, 50, seed=1)
        y0 = _position(readings(model, model.nominal(), q, {}))
        keep = []
        for j in js:
            x1 = model.nominal()
            x1[model.n_geometry:] = effect_vector(model, {f"gap.payload.{robot.joint_names[j]}": 1e-3})
            if np.sqrt(np.mean(np.sum((_position(readings(model, x1, q, {})) - y0) ** 2, axis=1))) > 1e-6:
                keep.append(j)
        js = keep
    return js


def _unit_effect(model, effect, joint, rng):
    """Effect parameters {name: value} of unit size with a random direction."""
    names = [n for n, e, j in zip(model.effect_names, model.effect_of, model.joint_of)
             if e == effect and (joint is None or j == joint)]
    if effect == "device_bias":
        v = np.concatenate([rng.normal(0, 0.3, 3), [rng.choice([-1.0, 1.0])]])
    else:
        v = rng.normal(size=len(names))
        v /= np.linalg.norm(v)
    return dict(zip(names, v))


def _decoy_readings(robot, model, x, q, cov, kind, rng):
    """Readings with an error outside the effect library, unit size before scaling."""
    y0 = readings(model, x, q, cov)
    n = robot.n_inputs
    if kind == "harmonic3":
        j = int(rng.integers(n))
        dq = np.zeros_like(q)
        dq[:, j] = np.sin(3 * q[:, j] + rng.uniform(0, 2 * np.pi))
        return y0, readings(model, x, q + 1e-3 * dq, cov), j
    if kind == "quadratic":
        j, k = rng.choice(n, 2, replace=False)
        span = max(np.ptp(q[:, k]), 1e-9)
        dq = np.zeros_like(q)
        dq[:, j] = ((q[:, k] - q[:, k].mean()) / span) ** 2
        return y0, readings(model, x, q + 1e-3 * dq, cov), int(j)
    p = _position(y0)
    c = p[rng.integers(len(p))]
    s = 0.3 * np.max(np.ptp(p, axis=0))
    u = rng.normal(size=3)
    bump = np.exp(-np.sum((p - c) ** 2, axis=1) / (2 * s**2))[:, None] * u / np.linalg.norm(u) * 1e-3
    return y0, _moved(y0, bump), -1


def _position(y):
    """The measured points (M, 3) of readings y: the pose's translation, each marker of a multi-marker reading."""
    if y.ndim == 3 and y.shape[1:] == (4, 4):
        return y[:, :3, 3]
    return y.reshape(-1, 3)


def _moved(y, disp):
    """Readings y with their measured points moved by disp (M, 3) (`_position`'s layout)."""
    y = np.array(y)
    if y.ndim == 3 and y.shape[1:] == (4, 4):
        y[:, :3, 3] += disp
        return y
    return y + disp.reshape(y.shape)


def device_frame(model, rng, wide: bool) -> np.ndarray:
    """Device parameters: within 5 cm / 0.05 rad of identity (narrow), or anywhere (wide: 1-4 m away in a random
    direction, turned by up to 180 degrees about a random axis, each marker up to 5 cm off its link)."""
    d = np.zeros(model.device.n_params)
    if not wide:
        d[:3] = rng.normal(0, 0.05, 3)
        d[3:6] = rng.normal(0, 0.05, 3)
        return d
    u, axis = rng.normal(size=3), rng.normal(size=3)
    d[:3] = rng.uniform(1.0, 4.0) * u / np.linalg.norm(u)
    d[3:6] = rng.uniform(0.0, np.pi) * axis / np.linalg.norm(axis)
    d[6:] = rng.uniform(-0.05, 0.05, len(d) - 6)  # each marker's offset on its link
    return d


def _scaled_effect(robot, model, x0, q, cov, eff, rng, target, separable):
    """Effect parameters of one effect at a random separable joint, scaled so that its RMS 3-D displacement is
    `target`: (joint or None, {name: value})."""
    joint = int(rng.choice(separable)) if eff in JOINT_EFFECTS else None
    unit = _unit_effect(model, eff, joint, rng)
    y0 = readings(model, x0, q, cov)
    x1 = x0.copy()
    x1[model.n_geometry:] = effect_vector(model, unit)
    disp = _position(readings(model, x1, q, cov)) - _position(y0)
    k = target / max(np.sqrt(np.mean(np.sum(disp**2, axis=1))), 1e-300)
    return joint, {kk: float(v * k) for kk, v in unit.items()}


def physical(model, x0, q, params) -> float:
    """Factor (<= 1) that brings every parameter of params within PHYSICAL_SHARE of the diagnosis' sane box
    (`gap.diagnose.box_limits`: 0.1 rad of joint or gravity deflection, 0.1 m, 10 % of a gain). Sized to a
    large noise, a gravity effect at a joint whose load barely changes over the poses needs a sag of tenths of a
    radian (seed 6: 0.16-0.36 rad at the Stanford arm's j1); no robot sags like that, so the draw is shrunk."""
    M, P = (np.asarray(a) for a in moment_norms(x0, q, model=model))
    lim = box_limits(model, M, P)
    index = {n: i for i, n in enumerate(model.effect_names)}
    over = max((abs(v) / (PHYSICAL_SHARE * lim[model.n_geometry + index[k]]) for k, v in params.items()), default=0.0)
    return min(1.0, 1.0 / over) if over > 0 else 1.0


def _device(robot, kind: str):
    """The device of a case: kind "multi_position" reads one marker at each tip of a tree."""
    return jc.make_device(kind, points=robot.n_tips) if kind == "multi_position" else jc.make_device(kind)


def _draw_robot(robots, rng) -> str:
    """A robot name: uniform over a sequence, or drawn with the weights of a {name: weight} mix."""
    if isinstance(robots, dict):
        names = list(robots)
        return str(rng.choice(names, p=np.asarray([robots[n] for n in names]) / sum(robots.values())))
    return str(rng.choice(list(robots)))


def _draw_kind(rng, wide: bool, closed: bool) -> str:
    """The hidden truth's kind: none 15 %, decoy 15 %, (closed loops: absorbed 10 %,) effect; wide: a units mistake
    in 6 % of the cases first."""
    if wide and rng.random() < 0.06:
        return "units"
    u = rng.random()
    if u < 0.15:
        return "none"
    if u < 0.3:
        return "decoy"
    return "absorbed" if closed and u < 0.4 else "effect"


def generate(folder, n_cases, seed, robots=ROBOTS, wide: bool = False):
    """Cases and labels (module docstring). wide: device frames anywhere, noise log-uniform 0.01-1 mm and stated
    to the diagnosis, a fifth of the effect cases with a second effect at once, a third of the cases as measurement
    CSV files (mm and degrees, or SI), 6 % with a units mistake (issue 17 item 4)."""
    os.makedirs(os.path.join(folder, "cases"), exist_ok=True)
    rng = np.random.default_rng(seed)
    labels = {}
    for i in range(n_cases):
        name = _draw_robot(robots, rng)
        robot = jc.robots.get(name)
        if robot.closure is not None:
            labels[f"{i:04d}"] = _generate_closed(folder, i, robot, rng, wide)
            continue
        if robot.n_tips > 1:
            device = "multi_position"
        else:
            device = "pose" if (name == "mrr1" and rng.random() < 0.25) else "position"
        model = gap_model(robot, _device(robot, device))
        n = int(rng.integers(30, 301))
        sigma = float(10 ** rng.uniform(-5, -3)) if wide else float(rng.choice([1e-5, 3e-5, 1e-4]))
        q = configurations(robot, n, int(rng.integers(1 << 30)))
        cov = {}
        if rng.random() < 0.6:
            cov["time"] = np.sort(rng.uniform(0, 3600, n))
        if rng.random() < 0.5:
            cov["temperature"] = 20 + 3 * np.sin(np.linspace(0, rng.uniform(1, 4), n)) + rng.normal(0, 0.05, n)
        if rng.random() < 0.5:
            cov["direction"] = rng.choice([-1.0, 1.0], (n, robot.n_inputs))
        kind = _draw_kind(rng, wide, closed=False)
        a = np.asarray(jc.perturb(robot, 1e-3, seed=int(rng.integers(1 << 30))))
        d = device_frame(model, rng, wide)
        x0 = np.concatenate([a, d, np.zeros(len(model.effect_names))])
        magnitude = float(rng.uniform(1, 10))
        target = magnitude * sigma * np.sqrt(3)  # RMS of the 3-D position displacement
        label = {"robot": name, "device": device, "n": n, "noise": sigma, "kind": kind, "covariates": sorted(cov)}
        if kind in ("none", "units"):
            y = readings(model, x0, q, cov)
            label.update(effect="none" if kind == "none" else "refused", joints=[], magnitude=0.0)
        elif kind == "decoy":
            dk = str(rng.choice(DECOYS))
            y0, y1, j = _decoy_readings(robot, model, x0, q, cov, dk, rng)
            disp = _position(y1) - _position(y0)
            k = target / max(np.sqrt(np.mean(np.sum(disp**2, axis=1))), 1e-300)
            y = _moved(y0, k * disp)
            label.update(effect="unexplained", decoy=dk, joints=[], magnitude=magnitude)
        else:
            effects = [e for e in JOINT_EFFECTS if separable_joints(robot, model, e)] + list(GLOBAL_EFFECTS)
            eff = str(rng.choice(effects))
            need = NEEDS.get(eff)
            if need == "time" or (need == "thermal" and "temperature" not in cov and "time" not in cov):
                cov.setdefault("time", np.sort(rng.uniform(0, 3600, n)))
            if need == "direction":
                cov.setdefault("direction", rng.choice([-1.0, 1.0], (n, robot.n_inputs)))
            label["covariates"] = sorted(cov)
            joint, params = _scaled_effect(robot, model, x0, q, cov, eff, rng, target, separable_joints(robot, model, eff))
            k = physical(model, x0, q, params)
            params, magnitude = {kk: v * k for kk, v in params.items()}, magnitude * k
            label.update(effect=eff, joints=[] if joint is None else [robot.joint_names[joint]], magnitude=magnitude,
                         parameters=params, physical_factor=k)
            if wide and rng.random() < 0.2:  # a second effect at once, of another kind, sized alike
                other = str(rng.choice([e for e in effects if e != eff]))
                if NEEDS.get(other) == "direction":
                    cov.setdefault("direction", rng.choice([-1.0, 1.0], (n, robot.n_inputs)))
                if NEEDS.get(other) in ("time", "thermal"):
                    cov.setdefault("time", np.sort(rng.uniform(0, 3600, n)))
                label["covariates"] = sorted(cov)
                joint2, params2 = _scaled_effect(robot, model, x0, q, cov, other, rng, target,
                                                 separable_joints(robot, model, other))
                k2 = physical(model, x0, q, params2)
                params2 = {kk: v * k2 for kk, v in params2.items()}
                params = {kk: params.get(kk, 0.0) + params2.get(kk, 0.0) for kk in {**params, **params2}}
                label.update(also=other, also_joints=[] if joint2 is None else [robot.joint_names[joint2]],
                             parameters=params)
            x1 = x0.copy()
            x1[model.n_geometry:] = effect_vector(model, params)
            y = readings(model, x1, q, cov)
        y = add_noise(_device(robot, device), y, sigma, sigma / 0.5, seed=int(rng.integers(1 << 30)))  # 1e-5 m ~ 2e-5 rad
        labels[f"{i:04d}"] = _save_case(folder, f"{i:04d}", robot, device, q, y, cov, sigma, wide, rng, label)
    _write_json(os.path.join(folder, "labels.json"), labels)


def _in_mm(y):
    """Readings y with their lengths in millimetres (a pose's rotation unchanged)."""
    if y.ndim == 3 and y.shape[1:] == (4, 4):
        y = np.array(y)
        y[:, :3, 3] *= 1e3
        return y
    return 1e3 * y


CSV_UNITS = {"csv_si": ("m", "rad"), "csv_mm_deg": ("mm", "deg"), "mm_as_m_csv": ("mm", "rad"), "deg_as_rad_csv": ("m", "deg")}


def _save_case(folder, key, robot, device, q, y, cov, sigma, wide, rng, label) -> dict:
    """Write case `key` (readings y in SI) and return its label with the format written.

    Narrow cases and two thirds of the wide ones: arrays in SI (npz). The other wide cases: a measurement CSV
    (`Dataset.to_csv`, 70 % in mm and degrees, else SI, stated in its `# units:` line) that the diagnosis reads with
    `Dataset.from_csv`; the per-joint direction covariate stays in the npz, as a log kept apart. A units-mistake
    case (label kind "units") is written wrong (`UNITS_MISTAKES`): a CSV in mm whose header says metres, a CSV in
    degrees whose header says radians, or arrays in mm handed over as metres. Its right answer is a refusal."""
    arrays = dict(q=q, robot=robot.name, device=device, **{f"cov_{k}": v for k, v in cov.items()})
    if wide:
        arrays["noise_figure"] = sigma  # the instrument's noise figure, known to its user
    if label["kind"] == "units":
        fmt = str(rng.choice(UNITS_MISTAKES))
    elif wide and rng.random() < 1 / 3:
        fmt = "csv_mm_deg" if rng.random() < 0.7 else "csv_si"
    else:
        fmt = "npz"
    if fmt in CSV_UNITS:
        from jaxcal.fit.csvfile import prismatic_joints

        length, angle = CSV_UNITS[fmt]
        logged = {k: v for k, v in cov.items() if k != "direction"}
        path = os.path.join(folder, "cases", f"{key}.csv")
        jc.Dataset(q=q, y=y, device=_device(robot, device), covariates=logged, joint_names=robot.joint_names).to_csv(
            path, length_unit=length, angle_unit=angle, prismatic=prismatic_joints(robot))
        if fmt in ("mm_as_m_csv", "deg_as_rad_csv"):  # the header states SI although the values are not
            with open(path) as fh:
                text = fh.read().replace(f"# units: length={length}, angle={angle}", "# units: length=m, angle=rad", 1)
            from jaxcal.io_atomic import write_text_atomic

            write_text_atomic(path, text)
        arrays["csv"] = f"{key}.csv"
    else:
        arrays["y"] = _in_mm(y) if fmt == "mm_as_m_array" else y
    np.savez(os.path.join(folder, "cases", f"{key}.npz"), **arrays)
    return dict(label, format=fmt)


def _generate_closed(folder, i, robot, rng, wide: bool = False):
    """One closed-loop case (position device); see the module docstring. Returns its label. wide: as for the
    serial cases (device frame anywhere, noise 0.01-1 mm stated, CSV files, units mistakes)."""
    model = gap_model(robot, jc.make_device("position"))
    n = int(rng.integers(30, 301))
    sigma = float(10 ** rng.uniform(-5, -3)) if wide else float(rng.choice([1e-5, 3e-5, 1e-4]))
    q = configurations(robot, n, int(rng.integers(1 << 30)))
    kind = _draw_kind(rng, wide, closed=True)
    cov = {}
    if rng.random() < 0.6:
        cov["time"] = np.sort(rng.uniform(0, 3600, n))
    if rng.random() < 0.5:
        cov["temperature"] = 20 + 3 * np.sin(np.linspace(0, rng.uniform(1, 4), n)) + rng.normal(0, 0.05, n)
    if rng.random() < 0.5 or kind == "effect":  # every effect is then a candidate (visibility needs its covariate)
        cov["direction"] = rng.choice([-1.0, 1.0], (n, robot.n_inputs))
    if kind == "effect":
        cov.setdefault("time", np.sort(rng.uniform(0, 3600, n)))
    d = device_frame(model, rng, wide)
    x0 = np.concatenate([np.asarray(jc.perturb(robot, 1e-3, seed=int(rng.integers(1 << 30)))), d, np.zeros(len(model.effect_names))])
    magnitude = float(rng.uniform(1, 10))
    target = magnitude * sigma * np.sqrt(3)
    label = {"robot": robot.name, "device": "position", "n": n, "noise": sigma, "kind": kind, "magnitude": magnitude}
    y0 = readings(model, x0, q, cov)
    if kind in ("none", "units"):
        y = y0
        label.update(effect="none" if kind == "none" else "refused", joints=[], magnitude=0.0)
    else:
        basis, E = geometry_basis(robot, model, x0, q, cov)
        if kind == "decoy":
            dk = str(rng.choice(DECOYS))
            _, y1, _ = _decoy_readings(robot, model, x0, q, cov, dk, rng)
            vis = visible_fraction(basis, y1 - y0)
            if vis < VISIBLE_MIN:  # a joint-space decoy the geometry absorbs: use a workspace bump instead
                dk = "bump"
                _, y1, _ = _decoy_readings(robot, model, x0, q, cov, dk, rng)
                vis = visible_fraction(basis, y1 - y0)
            disp = y1 - y0
            k = target / max(vis * np.sqrt(np.mean(np.sum(disp**2, axis=1))), 1e-300)  # the visible part at target
            y = y0 + k * disp
            label.update(effect="unexplained", decoy=dk, joints=[], visible=vis)
        else:
            options = []
            for eff in JOINT_EFFECTS + GLOBAL_EFFECTS:
                for j in (model.joints_with(eff) if eff in JOINT_EFFECTS else [None]):
                    unit = _unit_effect(model, eff, j, rng)
                    v = effect_vector(model, unit)
                    if not np.any(E @ v):  # no effect on these readings (its covariate is absent)
                        continue
                    vis = visible_fraction(basis, E @ v)
                    if (vis >= VISIBLE_MIN) == (kind == "effect") and (eff != "device_bias" or kind == "effect"):
                        options.append((eff, j, unit, vis))
            eff, joint, unit, vis = options[int(rng.integers(len(options)))]
            unit = {kk: 1e-3 * v for kk, v in unit.items()}  # a unit of 1 rad would open the loop for many samples
            x1 = x0.copy()
            x1[model.n_geometry:] = effect_vector(model, unit)
            disp = readings(model, x1, q, cov) - y0
            k = target / max(np.sqrt(np.mean(np.sum(disp**2, axis=1))), 1e-300)
            x1[model.n_geometry:] *= k
            y = readings(model, x1, q, cov)
            joints = [] if joint is None else [robot.joint_names[joint]]
            params = {kk: float(v * k) for kk, v in unit.items()}
            if kind == "effect":
                label.update(effect=eff, joints=joints, parameters=params, visible=vis)
            else:
                label.update(effect="none", joints=[], absorbed_effect=eff, absorbed_joints=joints, parameters=params, visible=vis)
    label["covariates"] = sorted(cov)
    y = add_noise("position", y, sigma, seed=int(rng.integers(1 << 30)))
    return _save_case(folder, f"{i:04d}", robot, "position", q, y, cov, sigma, wide, rng, label)


def _shard(folder, shard, only=None):
    """Case files of shard "i/n": cases sorted by (robot, device, padded size) so a process compiles few shapes;
    only: the robots whose cases to take (None: all)."""
    from jaxcal.gap.fit import padded_size

    files = sorted(f for f in os.listdir(os.path.join(folder, "cases")) if f.endswith(".npz"))
    if only is not None:
        files = [f for f in files if str(np.load(os.path.join(folder, "cases", f))["robot"]) in only]
    if shard is None:
        return files
    i, n = (int(v) for v in shard.split("/"))
    keyed = []
    for fn in files:
        z = np.load(os.path.join(folder, "cases", fn))
        keyed.append((str(z["robot"]), str(z["device"]), padded_size(len(z["q"])), fn))
    keyed.sort()
    chunk = int(np.ceil(len(keyed) / n))
    return [k[-1] for k in keyed[i * chunk:(i + 1) * chunk]]


def diagnose_all(folder, limit_s=None, shard=None, out_path=None, max_steps=None, twice: bool = False, only=None):
    """Diagnose the cases (reading only the case files); the predictions file is rewritten after each case.
    twice: diagnose each case a second time and record that call's wall time ("wall_again_s": everything compiled)."""
    out_path = out_path or os.path.join(folder, "predictions.json")
    preds = json.load(open(out_path)) if os.path.exists(out_path) else {}
    t_start = time.time()
    for fn in _shard(folder, shard, only):
        key = fn[:-4]
        if key in preds:
            continue
        if limit_s is not None and time.time() - t_start > limit_s:
            break
        z = np.load(os.path.join(folder, "cases", fn))
        robot = jc.robots.get(str(z["robot"]))
        options = {} if max_steps is None else {"max_steps": max_steps}
        if "noise_figure" in z.files:  # stated as a user states the tracker's figure (orientation: 2 x, rad per m)
            options.update(sigma_position=float(z["noise_figure"]), sigma_orientation=2.0 * float(z["noise_figure"]))
        t = time.perf_counter()
        try:
            data = _case_data(folder, z, robot)
            d = jc.gap.diagnose(robot, data, **options)
        except jc.DataError as exc:  # a refusal: the right answer to a units mistake, a wrong one otherwise
            preds[key] = {"verdict": "refused", "error": str(exc), "joints": [], "wall_s": time.perf_counter() - t}
            _write_json(out_path, preds)
            print(f"{key} {robot.name:<9} refused: {str(exc)[:100]}", flush=True)
            continue
        wall = time.perf_counter() - t
        again = None
        if twice:
            t = time.perf_counter()
            jc.gap.diagnose(robot, data, **options)
            again = time.perf_counter() - t
        preds[key] = {"verdict": d.verdict, "joints": list(d.joints), "shrink": d.shrink, "before": d.heldout_rms_before,
                      "after": d.heldout_rms_after, "floor": d.noise_floor, "structure_p": d.structure_p,
                      "selected": [[e, list(j)] for e, j in d.selected], "wall_s": wall, "wall_again_s": again,
                      "parameters": d.parameters, "diverged": d.diverged}
        _write_json(out_path, preds)
        print(f"{key} {d.robot_name:<9} {d.verdict:<13} {','.join(d.joints):<8} {wall:6.1f} s", flush=True)
        if compiled.mapped_regions() > MAX_MAPPED_REGIONS:  # before the process meets vm.max_map_count (jaxcal.compiled)
            compiled.clear()
    return preds


def _case_data(folder, z, robot):
    """The case's dataset as a user hands it over: from its measurement CSV (units from the file's header line) with
    the direction log attached, or from its arrays."""
    cov = {k[4:]: z[k] for k in z.files if k.startswith("cov_")}
    device = _device(robot, str(z["device"]))
    if "csv" in z.files:
        data = jc.Dataset.from_csv(os.path.join(folder, "cases", str(z["csv"])), joints=list(robot.joint_names), device=device)
        if "direction" in cov:
            data.covariates["direction"] = cov["direction"]
        return data
    return jc.Dataset(q=z["q"], y=z["y"], device=device, covariates=cov, joint_names=robot.joint_names)


def _median_again(preds, keys):
    """Median wall time of the second diagnosis of each case (`diagnose_all(twice=True)`), None when not timed."""
    again = [preds[k]["wall_again_s"] for k in keys if preds[k].get("wall_again_s") is not None]
    return float(np.median(again)) if again else None


def score(folder):
    labels = json.load(open(os.path.join(folder, "labels.json")))
    preds = {}
    for fn in sorted(f for f in os.listdir(folder) if f.startswith("predictions") and f.endswith(".json")):
        preds.update(json.load(open(os.path.join(folder, fn))))  # the shards' files (--predictions predictions_i.json)
    keys = sorted(k for k in preds if k in labels)
    conf = collections.defaultdict(collections.Counter)
    strong = right = 0
    joint_ok = joint_n = 0
    fa = fa_n = 0
    shrinks = []
    per_kind = collections.defaultdict(lambda: [0, 0])
    for k in keys:
        lab, pr = labels[k], preds[k]
        conf[lab["effect"] + ("+" + lab["also"] if "also" in lab else "")][pr["verdict"]] += 1
        ok = pr["verdict"] in (lab["effect"], lab.get("also"))  # two effects at once: naming either is top-1
        per_kind[lab["kind"]][0] += ok
        per_kind[lab["kind"]][1] += 1
        if lab["effect"] == "none":  # no effect, or one the geometry absorbs (closed loops)
            fa_n += 1
            fa += pr["verdict"] != "none"
        if lab["kind"] == "effect" and lab["magnitude"] >= 5 and lab["n"] >= 100:
            strong += 1
            right += ok
        if lab["kind"] == "effect" and ok:  # shrink recomputed from the recorded RMS values (position, mm)
            shrinks.append(shrink_fraction(pr["before"], pr["after"], pr["floor"]))
            named = lab["joints"] if pr["verdict"] == lab["effect"] else lab.get("also_joints", [])
            if named:
                joint_n += 1
                joint_ok += set(named) <= set(pr["joints"])
    effect_keys = [k for k in keys if labels[k]["kind"] == "effect"]
    units_keys = [k for k in keys if labels[k]["kind"] == "units"]
    res = {
        "cases": len(keys),
        "top1_strong": right / strong if strong else None, "n_strong": strong,
        "top1_all_effects": (sum(preds[k]["verdict"] in (labels[k]["effect"], labels[k].get("also")) for k in effect_keys)
                         / len(effect_keys)
                             if effect_keys else None),
        "right_joint": joint_ok / joint_n if joint_n else None, "n_joint": joint_n,
        "false_alarm": fa / fa_n if fa_n else None, "n_none": fa_n,
        "decoy_unexplained": (per_kind["decoy"][0] / per_kind["decoy"][1]) if per_kind["decoy"][1] else None,
        "n_decoy": per_kind["decoy"][1],
        "mean_shrink_right": float(np.mean(shrinks)) if shrinks else None,
        "units_refused": (sum(_refused_naming_unit(labels[k], preds[k]) for k in units_keys) / len(units_keys)
                          if units_keys else None),
        "n_units": len(units_keys),
        "false_refusals": sum(preds[k]["verdict"] == "refused" for k in keys if labels[k]["kind"] != "units"),
        "by_robot": _by_robot(labels, preds, keys),
        "median_wall_s": float(np.median([preds[k]["wall_s"] for k in keys])) if keys else None,
        "median_wall_again_s": _median_again(preds, keys),
        "confusion": {t: dict(c) for t, c in sorted(conf.items())},
        "by_magnitude": _by_magnitude(labels, preds, effect_keys),
    }
    return res


def _refused_naming_unit(label, pred) -> bool:
    """A units mistake answered right: refused, with an error that names the unit the values are in."""
    words = ("degree",) if label.get("format") == "deg_as_rad_csv" else ("mm", "millimetre")
    return pred["verdict"] == "refused" and any(w in pred.get("error", "") for w in words)


def _by_robot(labels, preds, keys):
    """Per robot: [right, cases] on effect cases >= 5x noise with >= 100 samples, on all effect cases, and on the
    other kinds (none, decoy, absorbed, units)."""
    out = {}
    for k in keys:
        lab, pr = labels[k], preds[k]
        row = out.setdefault(lab["robot"], {"strong": [0, 0], "effects": [0, 0], "other": [0, 0]})
        if lab["kind"] == "units":
            ok = _refused_naming_unit(lab, pr)
        else:
            ok = pr["verdict"] in (lab["effect"], lab.get("also"))
        strong = lab["magnitude"] >= 5 and lab["n"] >= 100
        groups = (["effects"] + (["strong"] if strong else [])) if lab["kind"] == "effect" else ["other"]
        for g in groups:
            row[g][0] += ok
            row[g][1] += 1
    return out


def _by_magnitude(labels, preds, keys):
    out = {}
    for lo, hi in ((1, 3), (3, 5), (5, 10.01)):
        for nlo, nhi in ((30, 100), (100, 301)):
            ks = [k for k in keys if lo <= labels[k]["magnitude"] < hi and nlo <= labels[k]["n"] < nhi]
            if ks:
                right = sum(preds[k]["verdict"] in (labels[k]["effect"], labels[k].get("also")) for k in ks)
                out[f"{lo}-{int(hi)}x, N {nlo}-{nhi - 1}"] = [right, len(ks)]
    return out


def table(res) -> str:
    pct = (lambda v: "n/a" if v is None else f"{100 * v:.0f} %")
    lines = ["| metric | value | target |", "|---|---|---|",
             f"| cases scored | {res['cases']} | |",
             f"| top-1, effects >= 5x noise and >= 100 samples | {pct(res['top1_strong'])} (n = {res['n_strong']}) | >= 90 % |",
             f"| top-1, all effect cases | {pct(res['top1_all_effects'])} | |",
             f"| right joint (verdict right, joint effects) | {pct(res['right_joint'])} (n = {res['n_joint']}) | >= 85 % |",
             f"| false alarms on no-effect cases | {pct(res['false_alarm'])} (n = {res['n_none']}) | <= 5 % |",
             f"| decoys answered \"unexplained\" | {pct(res['decoy_unexplained'])} (n = {res['n_decoy']}) | |",
             f"| mean shrink when the verdict is right | {pct(res['mean_shrink_right'])} | >= 90 % |",
             f"| units mistakes refused, naming the unit | {pct(res.get('units_refused'))} (n = {res.get('n_units', 0)}) | |",
             f"| other cases refused (false refusals) | {res.get('false_refusals', 0)} | 0 |",
             f"| median diagnose wall time | {res['median_wall_s']:.1f} s | |" if res["median_wall_s"] else "",
             f"| median wall time of a second diagnosis of the same case (compiled) | {res['median_wall_again_s']:.2f} s "
             "| <= 5 s |" if res.get("median_wall_again_s") else ""]
    lines += ["", "Confusion (rows: truth, columns: verdict):", ""]
    cols = sorted({v for c in res["confusion"].values() for v in c})
    lines.append("| truth \\ verdict | " + " | ".join(cols) + " |")
    lines.append("|---" * (len(cols) + 1) + "|")
    for t, c in res["confusion"].items():
        lines.append(f"| {t} | " + " | ".join(str(c.get(v, "")) for v in cols) + " |")
    if res.get("by_robot"):
        lines += ["", "By robot (right / cases): effects >= 5x noise with >= 100 samples; all effects; none, decoys, "
                  "absorbed and units mistakes:", "", "| robot | strong | all effects | other |", "|---|---|---|---|"]
        frac = lambda pair: f"{pair[0]}/{pair[1]}"  # noqa: E731
        lines += [f"| {r} | {frac(v['strong'])} | {frac(v['effects'])} | {frac(v['other'])} |"
                  for r, v in sorted(res["by_robot"].items())]
    lines += ["", "Top-1 by magnitude and sample count (right / cases): "
              + "; ".join(f"{k}: {v[0]}/{v[1]}" for k, v in res["by_magnitude"].items())]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--folder", default="/tmp/gap_blind")
    ap.add_argument("--limit-s", type=float, default=None, help="stop diagnosing after this many seconds (score what is done)")
    ap.add_argument("--stage", choices=("all", "generate", "diagnose", "score"), default="all")
    ap.add_argument("--shard", default=None, help="diagnose only shard i/n (parallel processes)")
    ap.add_argument("--predictions", default=None, help="predictions file (default FOLDER/predictions.json)")
    ap.add_argument("--robots", default=None, help="comma-separated robots to draw cases from (e.g. delta; default "
                    "mrr1,stanford, and with --wide the mix WIDE_MIX of serial arms, the two-arm tree and the Delta)")
    ap.add_argument("--max-steps", type=int, default=None, help="LM steps per fit in diagnose (default: diagnose's)")
    ap.add_argument("--wide", action="store_true", help="device frames anywhere, noise 0.01-1 mm stated to the diagnosis, "
                                                         "two effects at once in a fifth of the effect cases")
    ap.add_argument("--only", default=None, help="diagnose only the cases of these comma-separated robots")
    ap.add_argument("--twice", action="store_true", help="diagnose each case a second time, timing it apart (compiled)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "gap_blind"))
    args = ap.parse_args(argv)
    settings_path = os.path.join(args.folder, "settings.json")  # how the cases were made and diagnosed, for the scorer
    if args.stage in ("all", "generate") and not os.path.exists(os.path.join(args.folder, "labels.json")):
        robots = WIDE_MIX if (args.wide and args.robots is None) else tuple((args.robots or ",".join(ROBOTS)).split(","))
        generate(args.folder, args.cases, args.seed, robots, args.wide)
        _write_json(settings_path, {"cases_generated": args.cases, "seed": args.seed, "robots": robots,
                                    "wide": args.wide})
    if args.stage in ("all", "diagnose"):
        diagnose_all(args.folder, args.limit_s, args.shard, args.predictions, args.max_steps, args.twice,
                     None if args.only is None else args.only.split(","))
        settings = json.load(open(settings_path)) if os.path.exists(settings_path) else {}
        _write_json(settings_path, dict(settings, max_steps=args.max_steps))
    if args.stage in ("all", "score"):
        res = score(args.folder)
        res["settings"] = json.load(open(settings_path)) if os.path.exists(settings_path) else {}
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
        _write_json(args.out + ".json", res)
        md = table(res)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(args.out), suffix=".md")
        with os.fdopen(fd, "w") as fh:
            fh.write(md + "\n")
        os.replace(tmp, args.out + ".md")
        print(md)


if __name__ == "__main__":
    sys.exit(main())
