"""Position device ("position", aliases "tracker", "laser_tracker"): a laser tracker or any
instrument that reads one marker point on the tip link in its own frame, y = D^-1 T_tip m (3,).
Parameters: the device frame D (6) and the marker point m (3)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.measure.base import FRAME_INDEX, XYZ, Device, additive_noise, frame_from_params, frame_names
from jaxcal.measure.registry import register


class Position(Device):
    """One marker point read in the device frame."""

    kind = "position"
    residual_components = ("length",) * 3
    frame_index = FRAME_INDEX
    marker_reading = "point"

    @classmethod
    def build(cls) -> "Position":
        return cls.nominal_device(frame_names("dev") + frame_names("tool", XYZ), (3,))

    @property
    def n_points(self) -> int:
        return 1

    def read(self, tip, d):
        """y = D^-1 T_tip m with D = frame(d[0:6]), m = d[6:9]."""
        return frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:9]))

    def residual(self, pred, meas):
        """y_meas - y_pred (3,)."""
        return (meas - pred).reshape(-1)

    def split_errors(self, res):
        """(|r| per sample, None)."""
        return jnp.linalg.norm(res, axis=-1), None

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_position n, n (N, 3)."""
        return additive_noise(y, normal, sigma_position)

    def points(self, y):
        return y[:, None]


register(Position, "tracker", "laser_tracker")
