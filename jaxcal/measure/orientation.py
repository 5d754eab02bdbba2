"""Orientation device ("orientation", alias "inclinometer"): reads the rotation of a frame on the
tip link in its own frame, y = R_D^T R_tip R_M (3, 3). Parameters: the device rotation R_D (3)
and the marker rotation R_M (3), both rotation vectors; positions are not observed."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.kin.rotations import exp_so3, log_so3
from jaxcal.measure.base import Device, frame_names, rotation_noise
from jaxcal.measure.registry import register

RXYZ = ("rx", "ry", "rz")


class Orientation(Device):
    """One marker rotation read in the device frame."""

    kind = "orientation"
    residual_components = ("angle",) * 3

    @classmethod
    def build(cls) -> "Orientation":
        return cls.nominal_device(frame_names("dev", RXYZ) + frame_names("tool", RXYZ), (3, 3))

    def read(self, tip, d):
        """R_D^T R_tip R_M with R_D = exp(d[0:3]), R_M = exp(d[3:6])."""
        return exp_so3(d[0:3]).T @ tip.R @ exp_so3(d[3:6])

    def residual(self, pred, meas):
        """log(R_meas R_pred^T) (3,), the rotation vector of the difference (seed 001 eq 23-24)."""
        return log_so3(meas @ pred.T)

    def split_errors(self, res):
        """(None, |rotation vector|) per sample."""
        return None, jnp.linalg.norm(res, axis=-1)

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """exp(sigma_orientation n) R, n (N, 3)."""
        return rotation_noise(y, normal, sigma_orientation)


register(Orientation, "inclinometer")
