"""Pose device ("pose", aliases "location", "full_pose"): reads the full marker frame on the tip
link in its own frame, y = D^-1 T_tip M (4, 4). Parameters: the device frame D (6) and the marker
frame M (6)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.arrays import array_module, host_or_jax
from jaxcal.kin.rotations import log_so3
from jaxcal.measure.base import FRAME_INDEX, Device, additive_noise, frame_from_params, frame_names, rotation_noise
from jaxcal.measure.registry import register


class FullPose(Device):
    """One marker frame read in the device frame."""

    kind = "pose"
    residual_components = ("length",) * 3 + ("angle",) * 3
    frame_index = FRAME_INDEX
    marker_reading = "frame"

    @classmethod
    def build(cls) -> "FullPose":
        return cls.nominal_device(frame_names("dev") + frame_names("tool"), (4, 4))

    def read(self, tip, d):
        """Y = D^-1 T_tip M with D = frame(d[0:6]), M = frame(d[6:12]), as a 4x4 matrix."""
        return frame_from_params(d[0:6]).inverse().compose(tip.compose(frame_from_params(d[6:12]))).matrix()

    def residual(self, pred, meas):
        """(p_meas - p_pred, log(R_meas R_pred^T)) (6,): the orientation difference is the rotation
        vector of R_meas R_pred^T (seed 001 eq 23-24), never a difference of Euler angles."""
        dp = meas[:3, 3] - pred[:3, 3]
        return jnp.concatenate([dp, log_so3(meas[:3, :3] @ pred[:3, :3].T)])

    def split_errors(self, res):
        """(|position residual|, |rotation vector|) per sample."""
        return jnp.linalg.norm(res[:, :3], axis=-1), jnp.linalg.norm(res[:, 3:], axis=-1)

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """Position p + sigma_position n1, n1 (N, 3), then rotation exp(sigma_orientation n2) R, n2 (N, 3)."""
        y = host_or_jax(y)
        p = additive_noise(y[:, :3, 3], normal, sigma_position)
        R = rotation_noise(y[:, :3, :3], normal, sigma_orientation)
        if array_module(y, p, R) is jnp:
            return jnp.asarray(y).at[:, :3, 3].set(p).at[:, :3, :3].set(R)
        y = np.array(y, dtype=float)  # host readings (`simulate`): set in a copy
        y[:, :3, 3], y[:, :3, :3] = p, R
        return y

    def points(self, y):
        return y[:, None, :3, 3]

    def readings(self, y=None, R=None, p=None):
        """Readings (N, 4, 4) from y (N, 4, 4) or (N, 3, 4), or from rotations R (N, 3, 3) and positions p (N, 3)."""
        from jaxcal.fit.csvfile import DataError

        if y is None:
            if R is None or p is None:
                raise DataError("pose data needs y=(N, 4, 4) or both R=(N, 3, 3) and p=(N, 3)")
            R, p = np.asarray(R, float), np.asarray(p, float)
            y = np.zeros((len(R), 4, 4))
            y[:, :3, :3], y[:, :3, 3], y[:, 3, 3] = R, p, 1.0
        y = np.asarray(y, float)
        if y.shape[1:] == (3, 4):
            y = np.concatenate([y, np.broadcast_to([[[0, 0, 0, 1.0]]], (len(y), 1, 4))], axis=1)
        return y


register(FullPose, "location", "full_pose")
