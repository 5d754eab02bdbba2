"""The nine GECARO methods: autodiff Jacobians vs central differences, and noise-free recovery
of the base parameters by GECARO's iterated linearised least squares and by LM."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.fit.identifiable import calibrate
from jaxcal.fit.methods import METHODS, PLANE_METHODS, generate_points, observation_matrix, stacked_residual


@pytest.fixture(scope="module")
def stanford():
    return jc.robots.get("stanford")


@pytest.mark.parametrize("method", METHODS)
def test_observation_matrix_matches_central_fd(stanford, method):
    pts = generate_points(stanford, method, 4, seed=3)
    c = jnp.asarray(pts.plane)
    Qi, Qj, Y = (jnp.asarray(v) for v in (pts.Qi, pts.Qj, pts.Y))
    a = stanford.nominal_np + 0.01 * np.random.default_rng(0).standard_normal(stanford.n_params)
    nr = stanford.n_params
    x = np.concatenate([a, pts.plane])
    W = np.asarray(observation_matrix(stanford, method, jnp.asarray(a), c, Qi, Qj, Y))
    fd = central_fd(lambda x: stacked_residual(stanford, method, jnp.asarray(x[:nr]), jnp.asarray(x[nr:]), Qi, Qj, Y), x)
    assert rel_err(W, fd) < 1e-7  # measured ~1e-9 .. 1e-10 (central differences, h = 1e-6)


FAST = ("position", "plane1_unknown")


@pytest.mark.parametrize("method", [m if m in FAST else pytest.param(m, marks=pytest.mark.slow) for m in METHODS])
def test_recovers_base_parameters_noise_free(stanford, method):
    """True robot = nominal with only the base-set entries perturbed (regrouped ones stay nominal,
    so the base parameters are exactly the true values); points satisfy the constraints of the
    TRUE robot; calibration from nominal must return the true values."""
    rng = np.random.default_rng(7)
    ident = jc.identifiable(stanford, method, n_configs=40, seed=1)
    a_true = stanford.nominal_np.copy()
    base = [stanford.index(n) for n in ident.names]
    scale = np.array([0.02 if u == "gain" else 0.005 for u in stanford.units])
    a_true[base] += scale[base] * rng.uniform(-1, 1, len(base))
    pts = generate_points(stanford, method, 40, seed=2, a=a_true)
    c0 = pts.plane * (1 + 0.01 * (method in ("plane1_unknown", "plane2_unknown")))
    for solver in ("gecaro", "lm"):
        cal = calibrate(stanford, pts, c0=c0 if method in PLANE_METHODS else None, solver=solver)
        assert set(n for n in cal.estimated if not n.startswith("plane.")) == set(ident.names)
        assert np.max(np.abs(cal.a - a_true)) < 1e-9, (solver, np.max(np.abs(cal.a - a_true)))
        assert cal.rms[-1] < 1e-12
    assert cal.converged
