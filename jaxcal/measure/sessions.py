"""Measurement sessions: one instrument moved between sessions, so each session has its own device frame.

A robot measured on several days, with the tracker set up again each time, sees every session in a
different tracker frame D_s; the marker on the tool (and the robot) stay the same. `Sessions` wraps any
device kind: the parameters whose names start with a prefix in `per_session` (default "dev", the
device frame) get one copy per session, named `dev.<label>.x`, ...; the others (the marker `tool.*`)
are shared. One sample's reading is the wrapped device's reading flattened, followed by the index of
its session: y = (y_inner (flattened), s). The prediction is the wrapped device's reading in every
session's frame, and the residual is the wrapped device's residual in the sample's own session, so the
stacked residual, its weights and its degrees of freedom are those of the wrapped device.

`session_dataset(data)` builds the wrapped dataset from a dataset whose covariate "session" labels
each sample (`identify` does it by itself); the session frames are registered onto the readings one
session at a time (`frame_blocks`, used by `jaxcal.fit.core.registered_frame`).
"""

from __future__ import annotations

import dataclasses
import math
import re

import jax.numpy as jnp
import numpy as np

from jaxcal.arrays import array_module, host_or_jax
from jaxcal.measure.base import Device

SESSION = "session"  # the covariate that labels each sample's session


def _label_name(label: str) -> str:
    """A session label as it appears in parameter names: letters, digits, '_' and '-' kept, others '_'."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", str(label)) or "_"


def _layout(inner: Device, labels: tuple[str, ...], per_session: tuple[str, ...]):
    """(names, index): the wrapped device's parameter names, and for each session the (inner.n_params,)
    positions in the wrapped vector of the inner device's parameters in that session."""
    own = [i for i, n in enumerate(inner.names) if n.split(".")[0] in per_session]
    shared = [i for i in range(inner.n_params) if i not in own]
    names, index = [], np.zeros((len(labels), inner.n_params), int)
    for s, label in enumerate(labels):
        for i in own:
            prefix, rest = inner.names[i].split(".", 1)
            index[s, i] = len(names)
            names.append(f"{prefix}.{_label_name(label)}.{rest}")
    for i in shared:
        index[:, i] = len(names)
        names.append(inner.names[i])
    return tuple(names), index


@dataclasses.dataclass(frozen=True, eq=False)
class Sessions(Device):
    """The device `inner` read in one frame per session (`per_session` parameter prefixes copied per session)."""

    inner: Device = None
    labels: tuple[str, ...] = ()
    per_session: tuple[str, ...] = ("dev",)
    index: np.ndarray = None  # (sessions, inner.n_params): where each session's inner parameters sit

    kind = "sessions"
    marker_reading = None  # a reading is (inner reading, session index): clients on the geometry must not take it

    @classmethod
    def build(cls, inner: Device = None, labels=(), per_session=("dev",)) -> "Sessions":
        if not isinstance(inner, Device) or isinstance(inner, Sessions):
            raise ValueError("Sessions wraps one device (not another Sessions)")
        labels = tuple(str(v) for v in labels)
        if len(labels) < 1 or len(set(map(_label_name, labels))) != len(labels):
            raise ValueError(f"session labels must be distinct (after replacing characters other than letters, digits, "
                             f"'_' and '-'), got {labels}")
        per_session = tuple(per_session)
        names, index = _layout(inner, labels, per_session)
        if index.size and len(set(map(tuple, index))) == 1 and len(labels) > 1:
            raise ValueError(f"no parameter of the {inner.kind} device starts with {per_session}: nothing to give each "
                             "session")
        own = lambda arr: np.array([arr[np.flatnonzero(index == k)[0] % inner.n_params] for k in range(len(names))])  # noqa: E731
        return cls(names, own(inner.nominal_np), tuple(own(np.array(inner.units))), own(inner.free_mask).astype(bool),
                   (math.prod(inner.reading_shape) + 1,), inner=inner, labels=labels, per_session=per_session,
                   index=index)

    @property
    def residual_components(self) -> tuple[str, ...]:
        return self.inner.residual_components

    @property
    def sessions(self) -> int:
        return len(self.labels)

    @property
    def priority(self) -> np.ndarray:
        inner = self.inner.priority
        return np.array([inner[np.flatnonzero(self.index == k)[0] % self.inner.n_params] for k in range(self.n_params)])

    @property
    def error_unit(self) -> str:
        return self.inner.error_unit

    def session_params(self, d, s: int):
        """The wrapped device's parameter vector in session s."""
        return jnp.asarray(d)[jnp.asarray(self.index[s])]

    def check_robot(self, robot) -> None:
        self.inner.check_robot(robot)

    def read(self, tip, d):
        """The wrapped device's reading in every session's frame, flattened: (sessions * size,)."""
        return jnp.concatenate([self.inner.read(tip, self.session_params(d, s)).reshape(-1) for s in range(self.sessions)])

    def residual(self, pred, meas):
        """The wrapped device's residual in the sample's own session (meas[-1])."""
        shape = self.inner.reading_shape
        own = jnp.arange(self.sessions) == meas[-1]
        pred_s = jnp.sum(jnp.where(own[:, None], pred.reshape(self.sessions, -1), 0.0), axis=0)
        return self.inner.residual(pred_s.reshape(shape), meas[:-1].reshape(shape))

    def split_errors(self, res):
        return self.inner.split_errors(res)

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        y = host_or_jax(y)
        inner = self.inner.add_noise(y[:, :-1].reshape((len(y),) + self.inner.reading_shape), normal, sigma_position,
                                     sigma_orientation)
        xp = array_module(y, inner)
        return xp.concatenate([xp.reshape(inner, (len(y), -1)), xp.asarray(y)[:, -1:]], axis=1)

    def points(self, y):
        """The marker points of measured readings (N, size + 1), per the wrapped device."""
        y = np.asarray(y)
        return self.inner.points(y[:, :-1].reshape((len(y),) + self.inner.reading_shape))

    def predicted_points(self, pred):
        """The marker points of predicted readings in session 0's frame."""
        pred = np.asarray(pred)
        size = math.prod(self.inner.reading_shape)
        return self.inner.points(pred[:, :size].reshape((len(pred),) + self.inner.reading_shape))

    def frame_blocks(self, y):
        """[(indices in d of session s's 6-D frame, samples of session s)], for the wrapped devices with a frame
        when the frame is per session."""
        idx = self.inner.frame_index
        if idx is None or not all(self.inner.names[i].split(".")[0] in self.per_session for i in idx):
            return []
        s_of = np.asarray(y)[:, -1]
        return [(tuple(int(self.index[s, i]) for i in idx), s_of == s) for s in range(self.sessions)]

    def encode(self, data_y, session_labels) -> np.ndarray:
        """Readings (N, size + 1) from the wrapped device's readings and each sample's session label."""
        idx = session_indices(self.labels, session_labels)
        y = np.asarray(data_y, float)
        return np.concatenate([y.reshape(len(y), -1), idx[:, None].astype(float)], axis=1)


def session_indices(labels: tuple[str, ...], session_labels) -> np.ndarray:
    """The index into `labels` of each sample's label; a label not among them is an error that names it."""
    pos = {label: k for k, label in enumerate(labels)}
    given = [str(v) for v in np.asarray(session_labels).reshape(-1)]
    unknown = sorted(set(given) - set(pos))
    if unknown:
        raise ValueError(f"session label(s) {unknown} are not sessions of this calibration {list(labels)}; a new session "
                         "needs its own frame: see docs/identification.md, 'Sessions'")
    return np.array([pos[g] for g in given], int)


def sorted_labels(session_labels) -> tuple[str, ...]:
    """The distinct session labels in order of first appearance."""
    seen = []
    for v in np.asarray(session_labels).reshape(-1):
        if str(v) not in seen:
            seen.append(str(v))
    return tuple(seen)
