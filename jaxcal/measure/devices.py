"""Measurement devices: tool pose -> what the device reads.

Each device owns a block of parameters that is appended to the robot's parameter vector and
identified with it: the device frame D (its pose in the robot base frame; translation and
rotation vector, `dev.*`) and the marker on the tip link (`tool.*`). Both are unknown by default.
A reading is expressed in the device frame: y = D^-1 T_tip M.

| kind          | reading (one sample)            | parameters                  |
|---------------|---------------------------------|-----------------------------|
| "position"    | marker point, (3,)              | dev (6), tool point (3)     |
| "multi_position" | K marker points, (K, 3)      | dev (6), tool points (3 K)  |
| "pose"        | marker frame, (4, 4)            | dev (6), tool frame (6)     |
| "orientation" | marker rotation, (3, 3)         | dev rotation (3), tool (3)  |
| "three_point" | three sphere centres, (3, 3)    | dev (6); spheres known      |
| "theodolite"  | (azimuth, elevation) rad, (2,)  | dev (6), tool point (3)     |
| "laser_range" | distance to the marker m, (1,)  | dev x y z (3), tool (3)     |

Theodolite (seed 004 §4.2.3, §4.4.2): the sight line to the marker, v = D^-1 T_tip m, read as
the azimuth atan2(v_y, v_x) in the instrument's horizontal plane and the elevation
atan2(v_z, |v_xy|) above it (the thesis' zenith angle is pi/2 - elevation). Two angles give no
absolute scale, so some length must be known (the reference tree of §4.4.3: `locate_theodolite`).
Laser range: |D^-1 T_tip m|, the distance from the instrument centre; its orientation is not
observable and not a parameter. "inclinometer" is the "orientation" device.

"tracker" (a laser tracker with unknown base frame) is the "position" device.

Multi-marker position ("multi_position", alias "markers"; `make_device("multi_position", points=K)`):
K points rigid on the tip link, read together in one device frame, y = [D^-1 T_tip m_1, ...,
D^-1 T_tip m_K]; each point has its own unknown offset `tool.p<k>.x|y|z`, all sharing the one
device frame. Unlike "three_point" (a known target whose pose is read), the point offsets are
identified with the robot. Per-sample position error: RMS over the K points of the 3-D error.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import exp_so3, log_so3, skew

DEVICE_PRIORITY = 0.5  # below every robot parameter: the robot's own base frame is preferred
_FRAME = ("x", "y", "z", "rx", "ry", "rz")


def frame_from_params(v) -> Pose:
    """Pose from (x, y, z, rx, ry, rz) with (rx, ry, rz) a rotation vector."""
    return Pose(exp_so3(v[3:6]), v[0:3])


@dataclasses.dataclass(frozen=True, eq=False)
class Device:
    """A measurement device model. `read(pose, d)` maps one tool pose to one reading."""

    kind: str
    names: tuple[str, ...]
    nominal_np: np.ndarray
    units: tuple[str, ...]
    free_mask: np.ndarray
    reading_shape: tuple[int, ...]
    targets: np.ndarray | None = None  # three-point target: sphere centres in the tip frame (3, 3)

    @property
    def n_points(self) -> int:
        """Marker points per reading: K for "multi_position", 3 for "three_point", 1 for "position"."""
        return {"multi_position": self.reading_shape[0], "three_point": 3, "position": 1}.get(self.kind, 0)

    def _key(self):
        t = None if self.targets is None else np.asarray(self.targets).tobytes()
        return (self.kind, self.names, np.asarray(self.nominal_np).tobytes(), np.asarray(self.free_mask).tobytes(), t)

    def __hash__(self):  # by value, so equal devices share compiled solvers (static jit argument)
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, Device) and self._key() == other._key()

    @property
    def nominal(self):
        return jnp.asarray(self.nominal_np)

    @property
    def n_params(self) -> int:
        return len(self.names)

    @property
    def priority(self) -> np.ndarray:
        return np.full(self.n_params, DEVICE_PRIORITY)

    def known(self, *prefixes: str) -> "Device":
        """A copy with the parameters starting with the given prefixes ("dev", "tool") fixed."""
        mask = np.array([not any(n.startswith(p + ".") for p in prefixes) for n in self.names]) & self.free_mask
        return dataclasses.replace(self, free_mask=mask)

    def with_values(self, **values) -> "Device":
        """A copy whose nominal values are changed by name, e.g. with_values(**{'tool.z': 0.1})."""
        nom = self.nominal_np.copy()
        for k, v in values.items():
            nom[self.names.index(k)] = v
        return dataclasses.replace(self, nominal_np=nom)

    @property
    def frame_index(self):
        """Indices in d of the 6-D device frame (x, y, z, rx, ry, rz), or None."""
        return (0, 1, 2, 3, 4, 5) if self.names[:6] == _frame_names("dev") else None

    def points(self, y):
        """The positional part of readings y (N, ...) as points (N, K, 3) in the device frame, or None."""
        if self.kind == "position":
            return y[:, None, :]
        if self.kind in ("multi_position", "three_point"):
            return y
        if self.kind == "pose":
            return y[:, None, :3, 3]
        return None

    # -- the model -------------------------------------------------------------------------
    def read(self, tip: Pose, d):
        """Reading for one tool pose `tip` (in the robot base frame) and device parameters d."""
        if self.kind == "position":
            D = frame_from_params(d[0:6])
            return D.inverse().apply(tip.apply(d[6:9]))
        if self.kind == "multi_position":
            D = frame_from_params(d[0:6])
            return D.inverse().apply(tip.apply(d[6:].reshape(-1, 3)))
        if self.kind == "pose":
            D = frame_from_params(d[0:6])
            M = frame_from_params(d[6:12])
            return D.inverse().compose(tip.compose(M)).matrix()
        if self.kind == "orientation":
            return exp_so3(d[0:3]).T @ tip.R @ exp_so3(d[3:6])
        if self.kind == "three_point":
            D = frame_from_params(d[0:6])
            pts = jnp.asarray(self.targets)
            return D.inverse().apply(tip.apply(pts))
        if self.kind == "theodolite":
            return sight_angles(frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:9])))
        if self.kind == "laser_range":
            return jnp.linalg.norm(tip.apply(d[3:6]) - d[0:3], keepdims=True)
        raise ValueError(f"unknown device kind {self.kind!r}")

    def residual(self, pred, meas):
        """Residual vector of one sample: measured minus predicted (m and rad).

        Orientation differences are rotation vectors of R_meas R_pred^T (seed 001 eq 23-24),
        never differences of Euler angles.
        """
        if self.kind in ("position", "three_point", "multi_position"):
            return (meas - pred).reshape(-1)
        if self.kind == "pose":
            dp = meas[:3, 3] - pred[:3, 3]
            return jnp.concatenate([dp, log_so3(meas[:3, :3] @ pred[:3, :3].T)])
        if self.kind == "orientation":
            return log_so3(meas @ pred.T)
        if self.kind == "theodolite":
            d = meas - pred
            return jnp.arctan2(jnp.sin(d), jnp.cos(d))  # azimuth wraps at +-pi
        if self.kind == "laser_range":
            return meas - pred
        raise ValueError(f"unknown device kind {self.kind!r}")

    def split_errors(self, res):
        """(position error per sample (N,), orientation error per sample (N,) or None) from residuals (N, m)."""
        if self.kind == "position":
            return jnp.linalg.norm(res, axis=-1), None
        if self.kind in ("three_point", "multi_position"):
            r = res.reshape(res.shape[0], -1, 3)
            return jnp.sqrt(jnp.mean(jnp.sum(r**2, -1), -1)), None
        if self.kind == "pose":
            return jnp.linalg.norm(res[:, :3], axis=-1), jnp.linalg.norm(res[:, 3:], axis=-1)
        if self.kind == "laser_range":
            return jnp.abs(res[:, 0]), None
        return None, jnp.linalg.norm(res, axis=-1)


def sight_angles(v):
    """(azimuth, elevation) of a sight vector v (3,) in the instrument frame."""
    return jnp.stack([jnp.arctan2(v[1], v[0]), jnp.arctan2(v[2], jnp.hypot(v[0], v[1]))])


def _frame_names(prefix, parts=_FRAME):
    return tuple(f"{prefix}.{p}" for p in parts)


def make_device(kind: str, targets=None, points: int | None = None) -> Device:
    """A device of the given kind with nominal (identity) frames, all parameters unknown.
    `points`: the number K of marker points of a "multi_position" device."""
    kind = {"tracker": "position", "laser_tracker": "position", "location": "pose", "full_pose": "pose",
            "inclinometer": "orientation", "laser": "laser_range", "markers": "multi_position"}.get(kind, kind)
    if points is not None and kind != "multi_position":
        raise ValueError(f"points= is for the multi_position device, not {kind!r}")
    if kind == "multi_position":
        if points is None or int(points) != points or points < 1:
            raise ValueError(f"multi_position needs the number of marker points, points=K >= 1, got {points!r}")
        names = _frame_names("dev") + tuple(f"tool.p{k}.{a}" for k in range(1, int(points) + 1) for a in "xyz")
        shape = (int(points), 3)
    elif kind == "position":
        names = _frame_names("dev") + _frame_names("tool", ("x", "y", "z"))
        shape = (3,)
    elif kind == "pose":
        names = _frame_names("dev") + _frame_names("tool")
        shape = (4, 4)
    elif kind == "orientation":
        names = _frame_names("dev", ("rx", "ry", "rz")) + _frame_names("tool", ("rx", "ry", "rz"))
        shape = (3, 3)
    elif kind == "three_point":
        names = _frame_names("dev")
        shape = (3, 3)
        targets = np.array([[0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]]) if targets is None else np.asarray(targets, float)
        if targets.shape != (3, 3):
            raise ValueError(f"three_point targets must be 3 sphere centres (3, 3), got shape {targets.shape}")
    elif kind == "theodolite":
        names = _frame_names("dev") + _frame_names("tool", ("x", "y", "z"))
        shape = (2,)
    elif kind == "laser_range":
        names = _frame_names("dev", ("x", "y", "z")) + _frame_names("tool", ("x", "y", "z"))
        shape = (1,)
    else:
        raise ValueError(f"unknown device {kind!r}; expected position, tracker, multi_position (markers), pose, "
                         "orientation (inclinometer), three_point, theodolite or laser_range")
    units = tuple("angle" if n.split(".")[-1].startswith("r") else "length" for n in names)
    return Device(kind, names, np.zeros(len(names)), units, np.ones(len(names), bool), shape, targets)


def three_point_orientation(P_initial, P_final):
    """Rotation taking a three-point target from its initial to its final pose (seed 000 §3.3).

    Line vectors v1 = p2 - p1, v2 = p3 - p1 and v3 = v1 x v2 of both triads give
    R = [v'1 v'2 v'3][v1 v2 v3]^-1; noisy points make that matrix non-orthogonal, so it is
    projected onto SO(3) by the SVD (the closest rotation in the Frobenius norm).
    """

    def lines(P):
        v1, v2 = P[1] - P[0], P[2] - P[0]
        return jnp.stack([v1, v2, jnp.cross(v1, v2)], axis=1)

    A = lines(P_final) @ jnp.linalg.inv(lines(P_initial))
    U, _, Vt = jnp.linalg.svd(A)
    S = jnp.diag(jnp.array([1.0, 1.0, jnp.linalg.det(U @ Vt)]))
    return U @ S @ Vt


def locate_theodolite(points, readings, start=None, max_steps=100):
    """Theodolite frame parameters (x, y, z, rx, ry, rz) in the robot base frame from sightings of
    known reference points (the tree of seed 004 §4.4.3: three or more points, known by
    measurement, read as (azimuth, elevation)). Least squares by optimistix LM from `start`
    (default: the instrument 3 m away along -y looking at the points). Returns (params, rms rad)."""
    import optimistix as optx

    points = jnp.asarray(points, dtype=jnp.float64)
    readings = jnp.asarray(readings, dtype=jnp.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
        raise ValueError(f"locate_theodolite: need >= 3 known points (K, 3), got shape {points.shape}")
    if readings.shape != (points.shape[0], 2):
        raise ValueError(f"locate_theodolite: readings must be (K={points.shape[0]}, 2) azimuth/elevation, got {readings.shape}")

    def residual(d, _):
        pred = jax.vmap(lambda p: sight_angles(frame_from_params(d).inverse().apply(p)))(points)
        diff = readings - pred
        return jnp.arctan2(jnp.sin(diff), jnp.cos(diff)).ravel()

    if start is None:
        c = jnp.mean(points, axis=0)
        start = jnp.concatenate([c - jnp.array([0.0, 3.0, 0.0]), jnp.array([0.0, 0.0, jnp.pi / 2])])
    sol = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-14), jnp.asarray(start, jnp.float64),
                             max_steps=max_steps, throw=False)
    return sol.value, float(jnp.sqrt(jnp.mean(residual(sol.value, None) ** 2)))


__all__ = ["Device", "make_device", "three_point_orientation", "frame_from_params", "locate_theodolite", "sight_angles", "skew"]
