"""Multi-marker position device ("multi_position", alias "markers"; `make_device("multi_position",
points=K)`): K points rigid on the tip link read together in one device frame,
y = [D^-1 T_tip m_1, ..., D^-1 T_tip m_K] (K, 3). Each point has its own unknown offset
`tool.p<k>.x|y|z`, all sharing the device frame. Unlike "three_point" (a known target whose pose
is read), the point offsets are identified with the robot."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.measure.base import FRAME_INDEX, Device, additive_noise, frame_from_params, frame_names
from jaxcal.measure.registry import register


def rms_point_error(res):
    """Per-sample RMS over the points of the 3-D error, from residuals (N, 3 K)."""
    r = res.reshape(res.shape[0], -1, 3)
    return jnp.sqrt(jnp.mean(jnp.sum(r**2, -1), -1))


class PointSetDevice(Device):
    """Readings that are K points (N, K, 3) in the device frame: the residual, errors, noise and points
    shared by the multi-marker and three-point devices."""

    def residual(self, pred, meas):
        """y_meas - y_pred, flattened (3 K,)."""
        return (meas - pred).reshape(-1)

    def split_errors(self, res):
        """(RMS over the K points of the 3-D error, None)."""
        return rms_point_error(res), None

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_position n, n (N, K, 3)."""
        return additive_noise(y, normal, sigma_position)

    def points(self, y):
        return y


class MultiPosition(PointSetDevice):
    """K marker points read in one device frame."""

    kind = "multi_position"
    frame_index = FRAME_INDEX
    marker_reading = "points"

    @classmethod
    def build(cls, points: int | None = None) -> "MultiPosition":
        if points is None or int(points) != points or points < 1:
            raise ValueError(f"multi_position needs the number of marker points, points=K >= 1, got {points!r}")
        k = int(points)
        names = frame_names("dev") + tuple(f"tool.p{i}.{a}" for i in range(1, k + 1) for a in "xyz")
        return cls.nominal_device(names, (k, 3))

    @classmethod
    def for_readings(cls, y) -> "MultiPosition":
        """K from readings y of shape (N, K, 3)."""
        from jaxcal.fit.csvfile import DataError

        shape = np.shape(y) if y is not None else ()
        if len(shape) != 3 or shape[2] != 3:
            raise DataError(f"multi_position readings must have shape (N, K points, 3), got {shape or None}")
        return cls.build(points=shape[1])

    @property
    def n_points(self) -> int:
        return self.reading_shape[0]

    @property
    def residual_components(self) -> tuple[str, ...]:
        return ("length",) * (3 * self.n_points)

    def check_robot(self, robot) -> None:
        """A tree read at several bodies needs one marker point per tip (point k rides on `robot.tips[k]`)."""
        if robot.tips and len(robot.tips) != self.n_points:
            raise ValueError(f"robot {robot.name!r} is read at {len(robot.tips)} bodies (tips=), the multi_position "
                             f"device has {self.n_points} marker points: give one point per tip")

    def read(self, tip, d):
        """y_k = D^-1 T_tip m_k, m_k = d[6 + 3(k-1) : 9 + 3(k-1)]; with a stacked tip (K frames, a tree read at
        several bodies) point k is on frame k."""
        return frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:].reshape(-1, 3)))



register(MultiPosition, "markers")
