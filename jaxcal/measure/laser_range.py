"""Laser range device ("laser_range", alias "laser"): reads the distance from the instrument
centre c to a marker point m on the tip link, |T_tip m - c| (1,). Parameters: the centre c (3)
and the marker point m (3); the instrument's orientation is not observable and not a parameter."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.measure.base import XYZ, Device, additive_noise, frame_names
from jaxcal.measure.registry import register


class LaserRange(Device):
    """Distance from the instrument centre to one marker point."""

    kind = "laser_range"
    residual_components = ("length",)

    @classmethod
    def build(cls) -> "LaserRange":
        return cls.nominal_device(frame_names("dev", XYZ) + frame_names("tool", XYZ), (1,))

    def read(self, tip, d):
        """|T_tip m - c| with c = d[0:3], m = d[3:6], as (1,)."""
        return jnp.linalg.norm(tip.apply(d[3:6]) - d[0:3], keepdims=True)

    def residual(self, pred, meas):
        """d_meas - d_pred (1,)."""
        return meas - pred

    def split_errors(self, res):
        """(|range residual|, None) per sample."""
        return jnp.abs(res[:, 0]), None

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_position n, n (N, 1)."""
        return additive_noise(y, normal, sigma_position)


register(LaserRange, "laser")
