"""Simulated data with an injected effect (tests and the blind benchmark)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit.data import Dataset, _as_device
from jaxcal.gap.effects import GapModel, gap_model
from jaxcal.gap.fit import covariate_matrix, padded_size, predict
from jaxcal.kin.rotations import exp_so3


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


def add_noise(device_kind: str, y, sigma_position: float, sigma_orientation: float = 0.0, seed: int = 0):
    """Readings with Gaussian position noise (m) and a random small rotation (rad) for poses."""
    rng = np.random.default_rng(seed)
    y = np.array(y, float)
    if device_kind == "position":
        return y + sigma_position * rng.standard_normal(y.shape)
    y[:, :3, 3] += sigma_position * rng.standard_normal((len(y), 3))
    dR = np.asarray(jax.vmap(exp_so3)(jnp.asarray(sigma_orientation * rng.standard_normal((len(y), 3)))))
    y[:, :3, :3] = dR @ y[:, :3, :3]
    return y


def simulate_effect(robot, a_true, q, device="position", effects=None, covariates=None, noise=1e-5,
                    noise_orientation=1e-5, device_params=None, seed: int = 0) -> Dataset:
    """Dataset of a robot with geometry a_true and effect parameters {name: value} at joint readings q."""
    dev = _as_device(device)
    model = gap_model(robot, dev)
    d = dev.nominal_np if device_params is None else np.asarray(device_params, float)
    x = np.concatenate([np.asarray(a_true, float), d, effect_vector(model, effects or {})])
    covariates = covariates or {}
    y = add_noise(dev.kind, readings(model, x, q, covariates), noise, noise_orientation, seed)
    return Dataset(q=np.asarray(q, float), y=y, device=dev, covariates=covariates, joint_names=robot.joint_names)
