"""Simulated measurements of a perturbed robot (seed 004 §4.3)."""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np

from jaxcal.closure import forward_with_status
from jaxcal.fit import buckets
from jaxcal.fit.core import read_poses
from jaxcal.fit.data import Dataset
from jaxcal.forward import forward
from jaxcal.measure import as_device


def random_configurations(robot, n: int, seed: int = 0, margin: float = 0.0):
    """n joint vectors drawn uniformly within the robot's joint limits (shrunk by `margin`)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(robot.q_min), np.asarray(robot.q_max)
    span = hi - lo
    return lo + margin * span + (1 - 2 * margin) * span * rng.random((n, len(lo)))


def perturb(robot, scale=0.003, seed: int = 0, free_only: bool = True):
    """Parameters a = nominal + N(0, scale) on the (free) entries: the seed 000 §6 error draw.

    `scale` may be a number or a dict unit-kind -> standard deviation.
    """
    rng = np.random.default_rng(seed)
    a = np.array(robot.nominal_np, float)
    for i, u in enumerate(robot.units):
        if free_only and not robot.free_mask[i]:
            continue
        s = scale.get(u, 0.0) if isinstance(scale, dict) else scale
        a[i] += s * rng.standard_normal()
    return jnp.asarray(a)


def warn_unclosed(robot, status) -> np.ndarray:
    """Warns naming the samples whose closure status (`jaxcal.closure.closure_status`) is not CLOSED
    (their readings are the penalty pose of `jaxcal.closure.failed_pose`, not a measurement)."""
    from jaxcal.closure import STATUS_NAMES

    status = np.asarray(status)
    bad = np.flatnonzero(status != 0)
    if bad.size:
        kinds = ", ".join(f"{np.sum(status == k)} {STATUS_NAMES[k]}" for k in (1, 2) if np.any(status == k))
        warnings.warn(f"{robot.name}: {bad.size} of {len(status)} simulated sample(s) do not close ({kinds}): "
                      f"{bad[:20].tolist()}{' ...' if bad.size > 20 else ''}; their readings are penalty values, "
                      "not measurements: drop them before a fit (identify leaves out only the samples that do not "
                      "close at its starting parameters; these may close there)", stacklevel=3)
    return status


def _noise_levels(noise):
    if noise is None:
        return 0.0, 0.0, 0.0
    if np.isscalar(noise):
        return 0.0, float(noise), 0.0
    return float(noise.get("actuator", 0.0)), float(noise.get("position", 0.0)), float(noise.get("orientation", 0.0))


def simulate(robot, a_true, q, device="position", noise=None, device_params=None, seed: int = 0) -> Dataset:
    """Readings of the robot with parameters `a_true` at joint readings q.

    noise: None, a number (position standard deviation, m) or a dict with "actuator" (added to
    the joints before the direct model), "position" (m) and "orientation" (rad, a random
    rotation vector applied to the reading) standard deviations, as in seed 004 §4.3.
    The returned dataset holds the *recorded* joint values q (without actuator noise).
    """
    dev = as_device(device)
    dev.check_robot(robot)
    d = dev.nominal if device_params is None else jnp.asarray(device_params, dtype=jnp.float64)
    s_q, s_p, s_r = _noise_levels(noise)
    rng = np.random.default_rng(seed)
    q = np.asarray(q, float)
    q_actual = q + s_q * rng.standard_normal(q.shape)
    n = len(q)
    q_bucket = buckets.repeat_row(q_actual, buckets.sample_bucket(n), 0)  # one program per bucket of sample counts
    if robot.closure is not None:
        tips, status = forward_with_status(robot, a_true, q_bucket)
        warn_unclosed(robot, np.asarray(status)[:n])
    else:
        tips = forward(robot, jnp.asarray(a_true, dtype=jnp.float64), q_bucket)
    y = np.asarray(read_poses(dev, tips, d))[:n]
    y = np.asarray(dev.add_noise(y, rng.standard_normal, s_p, s_r))
    return Dataset(q=q, y=y, device=dev, joint_names=robot.joint_names)
