"""Simulated data with an injected effect (tests and the blind benchmark)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.fit.data import Dataset
from jaxcal.gap.fit import covariate_matrix, padded_size, predict
from jaxcal.gap.model import GapModel, gap_model
from jaxcal.measure import as_device


def effect_vector(model: GapModel, values: dict) -> np.ndarray:
    """Effect parameter vector e from {parameter name: value} (names as in model.effect_names)."""
    e = np.zeros(len(model.effect_names))
    for k, v in values.items():
        if k not in model.effect_names:
            raise KeyError(f"unknown effect parameter {k!r}; known: {model.effect_names}")
        e[model.effect_names.index(k)] = v
    return e


def readings(model: GapModel, x, q, covariates: dict):
    """Noise-free readings of the full model x at joint readings q with the given covariates."""
    n = len(q)
    C, _ = covariate_matrix(model, covariates, n)
    npad = padded_size(n)  # padded so that datasets of similar size share one compiled function
    qp = np.tile(model.robot.home_np, (npad, 1))
    qp[:n] = q
    Cp = np.zeros((npad, C.shape[1]))
    Cp[:n] = C
    return np.asarray(predict(jnp.asarray(x), jnp.asarray(qp), jnp.asarray(Cp), model=model))[:n]


def add_noise(device, y, sigma_position: float, sigma_orientation: float = 0.0, seed: int = 0):
    """Readings y with the device's measurement noise (`Device.add_noise`: Gaussian position noise (m),
    a random small rotation (rad) for poses) drawn from numpy's generator with `seed`; device: a
    Device or a kind name."""
    return np.array(as_device(device).add_noise(y, np.random.default_rng(seed).standard_normal, sigma_position,
                                                 sigma_orientation))


def simulate_effect(robot, a_true, q, device="position", effects=None, covariates=None, noise=1e-5,
                    noise_orientation=1e-5, device_params=None, seed: int = 0) -> Dataset:
    """Dataset of a robot with geometry a_true and effect parameters {name: value} at joint readings q."""
    dev = as_device(device)
    model = gap_model(robot, dev)
    d = dev.nominal_np if device_params is None else np.asarray(device_params, float)
    x = np.concatenate([np.asarray(a_true, float), d, effect_vector(model, effects or {})])
    covariates = covariates or {}
    y = add_noise(dev, readings(model, x, q, covariates), noise, noise_orientation, seed)
    return Dataset(q=np.asarray(q, float), y=y, device=dev, covariates=covariates, joint_names=robot.joint_names)
