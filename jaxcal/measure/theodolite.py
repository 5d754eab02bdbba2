"""Theodolite device ("theodolite"; seed 004 §4.2.3, §4.4.2): reads the direction of the sight
line to a marker point, v = D^-1 T_tip m, as the azimuth atan2(v_y, v_x) in the instrument's
horizontal plane and the elevation atan2(v_z, |v_xy|) above it (2,) (the thesis' zenith angle is
pi/2 - elevation). Parameters: the instrument frame D (6) and the marker point m (3). Two angles
carry no absolute scale, so some length must be known: the instrument is located from sightings
of known reference points (§4.4.3, `locate_theodolite`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcal.measure.base import FRAME_INDEX, XYZ, Device, additive_noise, frame_from_params, frame_names
from jaxcal.measure.registry import register


def sight_angles(v):
    """(azimuth, elevation) = (atan2(v_y, v_x), atan2(v_z, |v_xy|)) of a sight vector v (3,)."""
    return jnp.stack([jnp.arctan2(v[1], v[0]), jnp.arctan2(v[2], jnp.hypot(v[0], v[1]))])


def wrap_angle(a):
    """a wrapped to (-pi, pi]: atan2(sin a, cos a)."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


class Theodolite(Device):
    """Azimuth and elevation of one marker point seen from the instrument."""

    kind = "theodolite"
    residual_components = ("angle",) * 2
    frame_index = FRAME_INDEX

    @classmethod
    def build(cls) -> "Theodolite":
        return cls.nominal_device(frame_names("dev") + frame_names("tool", XYZ), (2,))

    def read(self, tip, d):
        """sight_angles(D^-1 T_tip m) with D = frame(d[0:6]), m = d[6:9]."""
        return sight_angles(frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:9])))

    def residual(self, pred, meas):
        """Angle differences y_meas - y_pred wrapped to (-pi, pi] (the azimuth wraps at +-pi)."""
        return wrap_angle(meas - pred)

    def split_errors(self, res):
        """(None, |angle residual|) per sample."""
        return None, jnp.linalg.norm(res, axis=-1)

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_orientation n, n (N, 2): angle noise (rad) on azimuth and elevation."""
        return additive_noise(y, normal, sigma_orientation)


def locate_theodolite(points, readings, start=None, max_steps=100):
    """Theodolite frame parameters (x, y, z, rx, ry, rz) in the robot base frame from sightings of
    known reference points (the reference tree of seed 004 §4.4.3: three or more points of known
    position, each read as (azimuth, elevation)), by optimistix Levenberg-Marquardt on the wrapped
    angle residuals from `start` (default: 3 m from the points' centroid along -y, looking along +y).
    Returns (params, RMS angle residual in rad)."""
    import optimistix as optx

    points = jnp.asarray(points, dtype=jnp.float64)
    readings = jnp.asarray(readings, dtype=jnp.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
        raise ValueError(f"locate_theodolite: need >= 3 known points (K, 3), got shape {points.shape}")
    if readings.shape != (points.shape[0], 2):
        raise ValueError(f"locate_theodolite: readings must be (K={points.shape[0]}, 2) azimuth/elevation, got {readings.shape}")

    def residual(d, _):
        pred = jax.vmap(lambda p: sight_angles(frame_from_params(d).inverse().apply(p)))(points)
        return wrap_angle(readings - pred).ravel()

    if start is None:
        c = jnp.mean(points, axis=0)
        start = jnp.concatenate([c - jnp.array([0.0, 3.0, 0.0]), jnp.array([0.0, 0.0, jnp.pi / 2])])
    sol = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-14), jnp.asarray(start, jnp.float64),
                             max_steps=max_steps, throw=False)
    return sol.value, float(jnp.sqrt(jnp.mean(residual(sol.value, None) ** 2)))


register(Theodolite)
