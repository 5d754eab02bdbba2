"""Every built-in robot with every device (issue 14): gradients of the weighted residual, the
simulate -> identify round trip on held-out samples, and a small Monte Carlo.

Each test uses a device frame rotated by ~1.1 rad and placed 1.6 m from the robot base (the
theodolite 2.9 m), readings through the closure for the closed loops, and float64.
"""

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from conftest import central_fd, rel_err
from helpers import configurations, covering, device, device_frame, robot, robot_device_grid

import jaxcal as jc
from jaxcal.fit.identify import residual_weights, residuals

NOISE = 1e-5  # simulated noise: m for positions and distances, rad for rotations and sight angles
NOISE_LEVELS = {"position": NOISE, "orientation": NOISE}

# Default-run cells: the gradient check touches every device and every robot but the slow ones; the
# round trip and the Monte Carlo (a solver compile per cell) run one open chain by default.
GRADIENT_FAST = covering([("mrr1", "position"), ("stanford", "pose"), ("ur10", "orientation"), ("tiago_arm", "three_point"),
                          ("talos_left_arm", "theodolite"), ("fourbar2d", "laser_range"), ("fourbar3d", "multi_position")])
ROUND_TRIP_FAST = [("mrr1", "position")]
MONTE_CARLO_FAST = [("mrr1", "position")]

MONTE_CARLO_XFAIL: dict = {}  # theodolite / laser_range crashed until Monte Carlo used the devices' own noise model
# The four-bars read by angles or ranges alone from the rotated frame 1.6-2.9 m away: the slow grid run of 2026-11-29
# (twelfth session, the tests' XLA flags) failed these cells, the first three on 374ac78 too (before the LM change of
# 37c07d7), with the same numbers. The fits are barely identifiable: fourbar2d-laser_range's estimate has a scaled
# condition number of 1e8 and moves j1.a, j4.a, j5.a by 0.10-0.26 m. Whether it converges is decided by round-off:
# 374ac78 converged, 37c07d7 stops 4 of its 24 fold solves and its last stage at 200 steps (485 iterations); with
# XLA's default flags, or with the LM's start damping at 1e-7 or 1e-8, 37c07d7 converges too.
ROUND_TRIP_XFAIL: dict = {
    ("fourbar2d", "theodolite"): "identify does not converge (373 iterations; 374ac78 and 37c07d7)",
    ("fourbar2d", "laser_range"): "identify does not converge under the tests' XLA flags (485 iterations; 374ac78 converged)",
    ("fourbar3d", "theodolite"): "held-out RMS 1.9e-2 against noise 1.2e-5 (374ac78 and 37c07d7)",
    ("fourbar3d", "laser_range"): "held-out RMS 5.4e-5 against noise 8.4e-6 (374ac78 and 37c07d7)",
}


def _full_point(name, kind):
    """Robot parameters with 1 mm / 1 mrad errors, then the rotated, translated device frame."""
    return np.concatenate([np.asarray(jc.perturb(robot(name), 1e-3, seed=2)), device_frame(kind)])


def _every_parameter_free(rb, x):
    """The robot as a fit that frees every parameter uses it (`Closure.serving`). The Delta's fast path holds only
    while its structure entries are at their Table 4.6 values; central differences move them, so the served robot
    is the Delta with the generic whole-tree closure (until issue 16 its fast path flagged every sample there
    and these cells were expected failures)."""
    if rb.closure is None:
        return rb
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Delta's note that the fit uses the generic closure
        return rb.closure.serving(rb, np.asarray(x[:rb.n_params]), np.ones(rb.n_params, bool))


@robot_device_grid(fast=GRADIENT_FAST)
def test_residual_gradient_matches_central_differences(robot_name, device_kind):
    """jacfwd of the stacked weighted residual w.r.t. all robot then device parameters vs central
    differences (h = 1e-6): relative error < 1e-6 (measured 1e-10 on open chains and four-bars,
    5e-8 on the Delta, scaling as 1/h: round-off of its closure solve)."""
    rb, dev = robot(robot_name), device(device_kind)
    q = jnp.asarray(configurations(robot_name, 4, seed=1))
    x0 = _full_point(robot_name, device_kind)
    rb = _every_parameter_free(rb, x0)
    y = jax.vmap(dev.read, (0, None))(jc.forward(rb, rb.nominal, q), jnp.asarray(device_frame(device_kind)))
    w = residual_weights(dev)
    f = jax.jit(lambda x: residuals(rb, dev, x, q, y, w).reshape(-1))
    J = np.asarray(jax.jit(jax.jacfwd(f))(jnp.asarray(x0)))
    err = rel_err(J, central_fd(lambda x: f(jnp.asarray(x)), x0))
    assert np.all(np.isfinite(J)) and err < 1e-6, f"{robot_name}/{device_kind}: relative error {err:.2e}"


def _samples(rb, dev):
    """Training samples: three residual components per estimable parameter, at least 30."""
    m = {"pose": 6, "orientation": 3}.get(dev.kind, int(np.prod(dev.reading_shape)))
    return max(30, math.ceil(3 * (int(rb.free_mask.sum()) + dev.n_params) / m))


def _held_out_rms(rb, dev, a_full, data):
    """RMS of the per-sample error (position, else orientation) of parameters a_full on data."""
    r = residuals(rb, dev, jnp.asarray(a_full), jnp.asarray(data.q), jnp.asarray(data.y), residual_weights(dev, 1.0, 1.0))
    pe, oe = dev.split_errors(r)
    return float(np.sqrt(np.mean(np.asarray(pe if pe is not None else oe) ** 2)))


@robot_device_grid(fast=ROUND_TRIP_FAST, xfail=ROUND_TRIP_XFAIL)
def test_round_trip_reaches_the_noise_level(robot_name, device_kind):
    """simulate -> identify from the nominal model: on 30 held-out samples the calibrated model's RMS
    error is < 2x that of the true model (the drawn noise itself). With n m >= 3 p residuals for p
    parameters the expected ratio is sqrt(1 + p / (n m)) <= 1.15; 2x leaves room for the spread of a
    30-sample RMS (~10 %)."""
    rb, dev = robot(robot_name), device(device_kind)
    x_true = _full_point(robot_name, device_kind)
    a_true, d_true = x_true[:rb.n_params], x_true[rb.n_params:]
    sim = lambda n, seed: jc.simulate(rb, a_true, configurations(robot_name, n, seed=seed), dev, noise=NOISE_LEVELS,  # noqa: E731
                                      device_params=d_true, seed=seed)
    train, test = sim(_samples(rb, dev), 5), sim(30, 6)
    fit = jc.identify(rb, train, sigma_position=NOISE, sigma_orientation=NOISE)
    rms, noise = _held_out_rms(rb, dev, fit.a_full, test), _held_out_rms(rb, dev, x_true, test)
    assert fit.converged, f"{robot_name}/{device_kind}: identify did not converge ({fit.iterations} iterations)"
    assert rms < 2 * noise, f"{robot_name}/{device_kind}: held-out RMS {rms:.3e} vs noise {noise:.3e}"


@robot_device_grid(fast=MONTE_CARLO_FAST, xfail=MONTE_CARLO_XFAIL)
def test_monte_carlo_runs_and_is_finite(robot_name, device_kind):
    """Four noisy identifications around the true device frame: every estimate is finite."""
    rb, dev = robot(robot_name), device(device_kind)
    x_true = _full_point(robot_name, device_kind)
    registered = dev.with_values(**dict(zip(dev.names, x_true[rb.n_params:])))
    q = configurations(robot_name, _samples(rb, dev), seed=5)
    mc = jc.uncertainty.monte_carlo(rb, x_true[:rb.n_params], q, device=registered, noise=NOISE_LEVELS, runs=4, chunk=4,
                                    devices=[], sigma_position=NOISE, sigma_orientation=NOISE)
    assert mc.estimates.shape == (4, len(mc.names)) and np.all(np.isfinite(mc.estimates))


# The core's data Jacobian (`core.data_residual_and_jacobian`): reverse mode sample by sample, for a closed mechanism
# after its closure is solved for the batch (`RobotDevice.presolve`); one open-chain cell per device by default.
CORE_JACOBIAN_FAST = [("mrr1", "position"), ("stanford", "pose"), ("ur10", "orientation"), ("tiago_arm", "three_point"),
                      ("talos_left_arm", "theodolite"), ("mrr1", "laser_range"), ("stanford", "multi_position")]
# (fourbar2d-position, ~20 s, runs with the slow tests: test_core.py checks the solver's Jacobian on the four-bar)


@robot_device_grid(fast=CORE_JACOBIAN_FAST)
def test_core_jacobian_is_jacfwd(robot_name, device_kind, monkeypatch):
    """The core's Jacobian of the weighted residual equals jax.jacfwd of it (float64, relative 1e-12), also when the
    samples are split into chunks with a remainder (chunk of 4 for 10 samples)."""
    from jaxcal.fit import core

    rb, dev = robot(robot_name), device(device_kind)
    model = core.RobotDevice(rb, dev)
    assert core.jacobian_mode(model) == "reverse"  # closed mechanisms too, since their presolve (2026-11-27)
    x = jnp.asarray(_full_point(robot_name, device_kind))
    q = jnp.asarray(configurations(robot_name, 10))
    y = jax.jit(lambda x: jax.vmap(dev.read, (0, None))(jc.forward(rb, x[:rb.n_params], q), x[rb.n_params:]))(x)  # compiled whole
    y = y + 1e-4 * jnp.sin(jnp.arange(y.size).reshape(y.shape))  # a non-zero residual
    w = jnp.asarray(core.per_sample(residual_weights(dev, 1e-3, 1e-3), 10))
    cov = jnp.zeros((10, 0))
    J_fwd = jax.jit(jax.jacfwd(lambda a: model.residuals(a, q, y, cov, w).reshape(-1)))(x)  # compiled: op by op was slower
    for chunk in (core.JACOBIAN_CHUNK, 4):
        monkeypatch.setattr(core, "JACOBIAN_CHUNK", chunk)  # read when traced: a new function per chunk size
        r, J = jax.jit(lambda a: core.data_residual_and_jacobian(model, a, q, y, cov, w))(x)
        np.testing.assert_allclose(r, model.residuals(x, q, y, cov, w).reshape(-1), rtol=0, atol=1e-11)  # readings ~1e3 weighted
        assert rel_err(J, J_fwd) < 1e-12, (chunk, rel_err(J, J_fwd))  # measured ~1e-16
