"""The measurement-device base class: what every device kind provides.

A device owns a block d of parameters appended to the robot's parameter vector and identified
with it, typically its frame D in the robot base frame (translation and rotation vector, `dev.*`)
and a marker on the tip link (`tool.*`); all unknown by default. One reading is what the device
sees of one tool pose T_tip, expressed in its own frame, e.g. y = D^-1 T_tip m for a marker point m.

A device kind is one subclass in one file (jaxcal/measure/<kind>.py): it sets `kind`,
`residual_components`, builds its parameter names in `build`, implements `read`, `residual`,
`split_errors` and `add_noise`, declares the capabilities that apply to it (`points`,
`frame_index`, `marker_reading`) and registers itself with `jaxcal.measure.registry.register`.
Clients ask these methods and properties, never the kind name, which is only for reports and files.

Devices are static arguments of compiled functions, so they compare and hash by value (class and
every field): two equal devices share compiled code.
"""

from __future__ import annotations

import abc
import dataclasses
import itertools
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.arrays import array_module, host_or_jax
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import exp_so3

DEVICE_PRIORITY = 6.0  # above every robot parameter (seed priorities 1-5): see the docstring of Device.priority
FRAME = ("x", "y", "z", "rx", "ry", "rz")
XYZ = ("x", "y", "z")
FRAME_INDEX = (0, 1, 2, 3, 4, 5)  # d[0:6] = (x, y, z, rx, ry, rz) of the device frame

Normal = Callable[[tuple], object]  # shape -> standard-normal draws of that shape


def frame_from_params(v) -> Pose:
    """Pose from (x, y, z, rx, ry, rz) with (rx, ry, rz) a rotation vector."""
    return Pose(exp_so3(v[3:6]), v[0:3])


def frame_names(prefix: str, parts=FRAME) -> tuple[str, ...]:
    """Parameter names `prefix.part`, e.g. ("dev.x", ..., "dev.rz")."""
    return tuple(f"{prefix}.{p}" for p in parts)


def additive_noise(y, normal: Normal, sigma):
    """y + sigma n, n standard normal of y's shape (one draw)."""
    y = host_or_jax(y)
    n = normal(np.shape(y))
    xp = array_module(y, n, sigma)
    return xp.asarray(y) + sigma * n


@jax.jit
def _rotated(v, R):
    """exp(v_i) R_i for rotation vectors v (N, 3) and rotations R (N, 3, 3): one program per N, not one per operation
    of `exp_so3`."""
    return jax.vmap(exp_so3)(v) @ R


def rotation_noise(R, normal: Normal, sigma):
    """dR R for each rotation R (N, 3, 3), dR = exp(sigma n) with n (N, 3) standard normal (one draw):
    a random small rotation applied in the reading frame."""
    R = host_or_jax(R)
    v = sigma * normal((np.shape(R)[0], 3))
    out = _rotated(jnp.asarray(v, dtype=jnp.float64), jnp.asarray(R, dtype=jnp.float64))
    return out if array_module(R, v) is jnp else np.asarray(out)


def key_normal(key) -> Normal:
    """A `normal(shape)` for `Device.add_noise` under jit/vmap: call i draws from fold_in(key, i)."""
    count = itertools.count()
    return lambda shape: jax.random.normal(jax.random.fold_in(key, next(count)), shape)


def _hashable(v):
    if isinstance(v, (np.ndarray, jax.Array)):
        a = np.asarray(v)
        return a.dtype.str, a.shape, a.tobytes()
    return v


@dataclasses.dataclass(frozen=True, eq=False)
class Device(abc.ABC):
    """A measurement device model: `read(tip, d)` maps one tool pose to one reading.

    Fields: parameter names, nominal values, units ("length" / "angle") and the free mask of the
    device's parameter block, and the shape of one reading. Subclasses may add fields (hashed too).
    """

    names: tuple[str, ...]
    nominal_np: np.ndarray
    units: tuple[str, ...]
    free_mask: np.ndarray
    reading_shape: tuple[int, ...]

    kind: ClassVar[str]  # registry name; reports and files only
    residual_components: ClassVar[tuple[str, ...]]  # "length" or "angle" per entry of one sample's residual
    frame_index: ClassVar[tuple[int, ...] | None] = None  # indices in d of the 6-D device frame, if any
    marker_reading: ClassVar[str | None] = None
    """What one reading is, for clients that work on the geometry directly (pose fitness, CSV, gap):
    "point": one marker point in the device frame, y = D^-1 T m (3,), with d = (frame (6), m (3));
    "points": K marker points, (K, 3); "frame": one marker frame, y = D^-1 T M (4, 4), with
    d = (frame (6), M (6)); None: anything else (angles, a distance, a rotation, a known target)."""

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def nominal_device(cls, names: tuple[str, ...], reading_shape: tuple[int, ...], **fields) -> "Device":
        """A device with all parameters zero (identity frames) and unknown; a name whose last part
        starts with "r" is an angle (rx, ry, rz), the others lengths."""
        units = tuple("angle" if n.split(".")[-1].startswith("r") else "length" for n in names)
        return cls(names, np.zeros(len(names)), units, np.ones(len(names), bool), reading_shape, **fields)

    @classmethod
    @abc.abstractmethod
    def build(cls) -> "Device":
        """The device with nominal (identity) frames, all parameters unknown; keyword options per kind."""

    @classmethod
    def for_readings(cls, y) -> "Device":
        """The device that reads y, for a device named without options (`as_device`)."""
        return cls.build()

    # -- value semantics -------------------------------------------------------------------------
    def _key(self):
        """The device's value (its type and fields), computed once: a device is frozen, and the solvers' caches
        hash it on every call (~60 times an `identify`, 13 us each)."""
        key = self.__dict__.get("_value_key")
        if key is None:
            key = (type(self),) + tuple(_hashable(getattr(self, f.name)) for f in dataclasses.fields(self))
            object.__setattr__(self, "_value_key", key)
        return key

    def __getstate__(self):  # the fields alone: a pickle (`jaxcal.exported`'s fingerprint) must not see the cache
        return {k: v for k, v in self.__dict__.items() if k != "_value_key"}

    def __hash__(self):  # by value, so equal devices share compiled solvers (static jit argument)
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, Device) and self._key() == other._key()

    # -- the parameter block ---------------------------------------------------------------------
    @property
    def nominal(self):
        return jnp.asarray(self.nominal_np)

    @property
    def n_params(self) -> int:
        return len(self.names)

    @property
    def priority(self) -> np.ndarray:
        """Base-set priority of the device parameters: above every robot parameter (seed 001 §4 uses 1-5).

        Where a device parameter and robot parameters are exactly redundant (the tracker's frame and the robot's
        base link, the marker and the last link, the first joint's offset and the frame's yaw), the device one is
        estimated and the robot ones stay at their prior: the robot's table only ever takes calibration-sized
        corrections, and the unknown frames, which have no prior worth keeping, take the rest. With the robot
        preferred, a start whose frames were fitted on the nominal robot along a weakly determined direction
        left its error to the robot (a probe that barely turns: the base height moved 0.52 m)."""
        return np.full(self.n_params, DEVICE_PRIORITY)

    @property
    def n_points(self) -> int:
        """Marker points per reading (0 when the reading is not a set of points)."""
        return 0

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

    def check_robot(self, robot) -> None:
        """Raise ValueError when a reading cannot be taken from what `forward(robot, ...)` returns: one tool
        frame, or for a tree read at several bodies (`robot.tips`) one frame per marker slot."""
        if robot.tips:
            raise ValueError(f"robot {robot.name!r} is read at {len(robot.tips)} bodies (tips=); the {self.kind} device "
                             f"reads one tool frame: use make_device('multi_position', points={len(robot.tips)}), "
                             "marker k on tip k")

    # -- the model -------------------------------------------------------------------------------
    @abc.abstractmethod
    def read(self, tip: Pose, d):
        """Reading for one tool pose `tip` (in the robot base frame) and device parameters d."""

    @abc.abstractmethod
    def residual(self, pred, meas):
        """Residual vector of one sample, measured minus predicted (m, rad); entry i is a
        `residual_components[i]` quantity."""

    @abc.abstractmethod
    def split_errors(self, res):
        """(position error per sample (N,) or None, orientation error per sample (N,) or None)
        from residuals (N, m)."""

    @abc.abstractmethod
    def add_noise(self, y, normal: Normal, sigma_position, sigma_orientation):
        """Noisy readings from exact ones y (N, *reading_shape): the device's measurement noise,
        standard deviations sigma_position (m) and sigma_orientation (rad), drawn by `normal(shape)`
        (numpy's `rng.standard_normal`, or `key_normal(key)` under jit) in a fixed order."""

    def weights(self, sigma_position, sigma_orientation):
        """Weights (m,) of one sample's residual: 1/sigma_position on length entries,
        1/sigma_orientation on angle entries (whitening by the a-priori noise levels)."""
        length = np.array([c == "length" for c in self.residual_components])
        return np.where(length, 1.0 / sigma_position, 1.0 / sigma_orientation)

    @property
    def error_unit(self) -> str:
        """Unit of the reported RMS error: "mm" when the residual has a length entry, else "mrad"."""
        return "mm" if "length" in self.residual_components else "mrad"

    def readings(self, y=None, R=None, p=None):
        """Readings as a float array from the arguments of `Dataset`; y for every device, a device
        with other input forms reads those too (pose: rotations R and positions p)."""
        from jaxcal.fit.csvfile import DataError

        if y is None:
            raise DataError(f"{self.kind} data needs readings y")
        return np.asarray(y, float)

    def points(self, y):
        """The positional part of readings y (N, *reading_shape) in the device frame, (N, K, 3);
        None for a device whose readings hold no point."""
        return None

    def predicted_points(self, pred):
        """`points` of the model's predicted readings (`jaxcal.fit.core.readings`); the same as `points` unless a
        prediction is laid out unlike a measured reading (`measure.sessions`)."""
        return self.points(pred)

    def frame_blocks(self, y):
        """[(indices in d of a 6-D device frame, the samples of readings y (N, ...) taken in it)]: the frames the
        start registers onto the readings (`jaxcal.fit.core.registered_frame`); one per session for
        `measure.sessions.Sessions`."""
        return [] if self.frame_index is None else [(self.frame_index, np.ones(len(y), bool))]
