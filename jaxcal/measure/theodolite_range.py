"""Theodolite with a built-in laser range finder ("theodolite_range", alias "total_station"; seed 004
§4.4.2: "a single theodolite with a laser range finder built in", angles to seconds of arc, distance
to +-1 mm): reads the sight vector to a marker point, v = D^-1 T_tip m, as (azimuth, elevation, range)
= (atan2(v_y, v_x), atan2(v_z, |v_xy|), |v|) (3,). Parameters: the instrument frame D (6) and the
marker point m (3). Unlike the angles alone, the range fixes the scale and the instrument's distance;
a reading converts back to the point v in the instrument frame (`points`), so the instrument frame
can be started by rigid registration like a position device's."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.arrays import array_module, host_or_jax
from jaxcal.measure.base import FRAME_INDEX, XYZ, Device, frame_from_params, frame_names
from jaxcal.measure.registry import register
from jaxcal.measure.theodolite import sight_angles, wrap_angle


def sight_reading(v):
    """(azimuth, elevation, range) of a sight vector v (3,)."""
    return jnp.concatenate([sight_angles(v), jnp.linalg.norm(v, keepdims=True)])


def sight_vector(y):
    """The sight vectors (..., 3) of readings y (..., 3) = (azimuth, elevation, range): the inverse
    of `sight_reading`, r (cos el cos az, cos el sin az, sin el)."""
    az, el, r = y[..., 0], y[..., 1], y[..., 2]
    return jnp.stack([r * jnp.cos(el) * jnp.cos(az), r * jnp.cos(el) * jnp.sin(az), r * jnp.sin(el)], axis=-1)


class TheodoliteRange(Device):
    """Azimuth, elevation and distance of one marker point seen from the instrument."""

    kind = "theodolite_range"
    residual_components = ("angle", "angle", "length")
    frame_index = FRAME_INDEX

    @classmethod
    def build(cls) -> "TheodoliteRange":
        return cls.nominal_device(frame_names("dev") + frame_names("tool", XYZ), (3,))

    def read(self, tip, d):
        """sight_reading(D^-1 T_tip m) with D = frame(d[0:6]), m = d[6:9]."""
        return sight_reading(frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:9])))

    def residual(self, pred, meas):
        """y_meas - y_pred with the two angle differences wrapped to (-pi, pi]."""
        diff = meas - pred
        return jnp.concatenate([wrap_angle(diff[..., :2]), diff[..., 2:]], axis=-1)

    def split_errors(self, res):
        """(|range residual|, |angle residual|) per sample."""
        return jnp.abs(res[:, 2]), jnp.linalg.norm(res[:, :2], axis=-1)

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + (sigma_orientation, sigma_orientation, sigma_position) n, n (N, 3) standard normal, one draw."""
        y = host_or_jax(y)
        n = normal(np.shape(y))
        xp = array_module(y, n, sigma_position, sigma_orientation)
        return xp.asarray(y) + xp.stack([sigma_orientation, sigma_orientation, sigma_position]) * n

    @property
    def n_points(self) -> int:
        return 1

    def points(self, y):
        """The marker point in the instrument frame, (N, 1, 3), from the readings."""
        return sight_vector(jnp.asarray(y))[:, None, :]


register(TheodoliteRange, "total_station")
