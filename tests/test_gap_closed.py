"""Gap diagnosis on closed-loop robots (issue 7 part c): the Delta's effect library through the closure,
gradients against central differences, the load and thermal models against independent computations,
injected effects recovered with their parameters (slow: the Delta diagnosis compiles for ~1-2 min)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import delta as dl
from jaxcal.gap.closed import CLOSED_EFFECTS, PLATFORM_MASS, delta_workspace, platform_load, platform_loads
from jaxcal.gap.effects import gap_model, residuals
from jaxcal.gap.fit import covariate_matrix
from jaxcal.gap.simulate import add_noise, effect_vector, readings

NOISE = 2e-5
N_SMALL = 6  # samples of the derivative / identity checks (one compiled shape)


@pytest.fixture(scope="module")
def delta():
    return jc.robots.get("delta")


@pytest.fixture(scope="module")
def model(delta):
    return gap_model(delta, jc.make_device("position"))


def _covariates(n, seed=0):
    rng = np.random.default_rng(seed)
    return {"time": np.linspace(0.0, 3600.0, n), "temperature": 20 + 2 * np.sin(np.linspace(0, 3, n)) + rng.normal(0, 0.02, n),
            "direction": rng.choice([-1.0, 1.0], (n, 3))}


def test_closed_model_names_the_actuators(delta, model):
    """Same effect names as the open-chain library, one joint effect per actuator (robot.joint_names);
    link_bending is not in the closed-loop library."""
    assert set(model.effect_of) == set(CLOSED_EFFECTS) and "link_bending" not in model.effect_of
    for j, name in enumerate(delta.joint_names):
        assert f"gap.gear.{name}.s1" in model.effect_names and f"gap.compliance.{name}" in model.effect_names
        assert model.joints_with("backlash")[j] == j
    assert model.revolute == (True, True, True)
    assert model.n_params == delta.n_params + 9 + len(model.effect_names)


def test_actuator_effects_are_the_closed_forward_at_corrected_inputs(delta, model):
    """gear + backlash + gain + coupling + compliance = jc.forward at q + dq, dq written out by hand
    (seed 001 eq 4 for the joint-space terms; compliance c_j tau_j with the platform load)."""
    q = delta_workspace(N_SMALL, seed=4)
    cov = _covariates(N_SMALL, seed=1)
    vals = {"gap.gear.theta1.s1": 2e-3, "gap.gear.theta1.c2": -1e-3, "gap.backlash.theta2": 1.5e-3,
            "gap.encoder_gain.theta3": 2e-3, "gap.coupling.theta2": -1e-3, "gap.compliance.theta3": 3e-3}
    x = np.concatenate([delta.nominal_np, np.zeros(9), effect_vector(model, vals)])
    y = readings(model, x, q, cov)
    tau = np.asarray(jax.vmap(functools.partial(platform_load, delta))(jnp.asarray(q)))
    dq = np.zeros_like(q)
    dq[:, 0] = 2e-3 * np.sin(q[:, 0]) - 1e-3 * np.cos(2 * q[:, 0])
    dq[:, 1] = 1.5e-3 * np.sign(cov["direction"][:, 1]) - 1e-3 * q[:, 0]
    dq[:, 2] = 2e-3 * q[:, 2] + 3e-3 * tau[:, 2]
    want = np.asarray(jc.forward(delta, delta.nominal, q + dq).p)  # position device at its nominal (identity) frame
    assert np.max(np.abs(y - want)) < 1e-12


def test_platform_load_matches_the_nominal_direct_solution(delta):
    """tau_j = m g_hat . dP/dtheta_j: the closed Table 4.6 model (jacfwd through the closure; sample by sample and for
    the batch) against central differences of the independent nominal direct solution (eq 2.135-2.146). Table 4.6 rounds the nacelle
    points to 4 digits (P off by <= 4e-5 m), so the two agree to ~1e-4 relative, not to rounding."""
    q = delta_workspace(N_SMALL, seed=5)
    tau = np.asarray(jax.vmap(functools.partial(platform_load, delta))(jnp.asarray(q)))

    def load(e):  # m g_hat . P with g_hat = -z, every sample's actuators moved by e
        return -PLATFORM_MASS * np.asarray(jax.vmap(dl.direct)(jnp.asarray(q + e))[0])[:, 2]

    fd = central_fd(load, np.zeros(3), h=1e-6)
    rel = rel_err(tau, fd)
    assert rel < 1e-3, rel
    assert np.all(np.abs(fd) > 0.05)  # a load worth modelling on every actuator
    # the batch's loads (closure solved once for the batch, then each sample's implicit step): the same numbers
    assert np.max(np.abs(np.asarray(jax.jit(functools.partial(platform_loads, delta))(jnp.asarray(q))) - tau)) < 1e-12


@pytest.mark.slow  # ~33 s (CI time); the thermal effect's gradient through the closure is checked fast below
def test_thermal_scaling_is_a_similarity_of_the_closed_mechanism(delta, model):
    """Scaling every length of the Delta by s and closing the loop again puts the tool at s p (angles
    unchanged): the thermal effect's p0 + (1 + kappa tau)(p - p0) is exact through the closure."""
    q = delta_workspace(N_SMALL, seed=6)
    s = 1.0 + 3e-3
    a = np.asarray(jc.perturb(delta, 1e-3, seed=7))
    lengths = np.array([u == "length" for u in delta.units])
    a_s = np.where(lengths, s * a, a)
    p = np.asarray(jc.forward(delta, a, q).p)
    p_s = np.asarray(jc.forward(delta, a_s, q).p)
    assert np.max(np.abs(p_s - s * p)) < 1e-12
    cov = {"temperature": np.linspace(18.0, 24.0, N_SMALL)}
    C, _ = covariate_matrix(model, cov, N_SMALL)
    x = np.concatenate([a, np.zeros(9), effect_vector(model, {"gap.thermal": 1e-3})])
    y = readings(model, x, q, cov)
    assert np.max(np.abs(y - (1 + 1e-3 * C[:, 1:2]) * p)) < 1e-12


def test_effect_gradients_through_the_closure_match_central_differences(delta, model):
    """jacfwd of the weighted residuals (closure inside, IFT derivatives) against central differences,
    on every effect parameter and a few geometry / device entries. Measured relative error 2e-10 overall,
    <= 1.2e-9 per column; bounds 1e-6 and 1e-5."""
    n = N_SMALL
    q = jnp.asarray(delta_workspace(n, seed=8))
    C, _ = covariate_matrix(model, _covariates(n), n)
    C = jnp.asarray(C)
    rng = np.random.default_rng(0)
    x = np.asarray(model.nominal()).copy()
    x[:delta.n_params] = np.asarray(jc.perturb(delta, 1e-3, seed=1))
    x[delta.n_params:delta.n_params + 3] = [0.02, -0.01, 0.03]
    x[model.n_geometry:] = 1e-3 * rng.standard_normal(len(model.effect_names))
    y = jnp.asarray(readings(model, x, np.asarray(q), {}))
    w = jnp.ones((n, 3)) * 1e3
    cols = np.concatenate([[delta.index("j2.a3"), delta.index("j7.d1"), delta.index("j12.d3"), delta.n_params + 4],
                           np.arange(model.n_geometry, model.n_params)])

    @jax.jit
    def f(v):
        return residuals(model, jnp.asarray(x).at[cols].set(v), q, y, C, w).reshape(-1)

    J = np.asarray(jax.jacfwd(f)(jnp.asarray(x[cols])))
    J_fd = central_fd(f, x[cols], h=1e-6)
    err = rel_err(J, J_fd)
    assert err < 1e-6, err
    for k, c in enumerate(cols):  # column by column, so a wrong effect cannot hide behind a large one
        assert rel_err(J[:, k], J_fd[:, k]) < 1e-5, model.names[c]


# ---- injected effects recovered by the diagnosis (slow: the Delta diagnosis compiles its solvers) ----------
def _case(delta, model, effects, times_noise=8.0, n=150, seed=0, noise=NOISE, frame=(0.03, -0.02, 0.01)):
    """Readings with the effects sized to times_noise x the noise; frame: the tracker's position (3) or pose (6)."""
    q = delta_workspace(n, seed=seed + 1)
    cov = _covariates(n, seed)
    x0 = np.concatenate([np.asarray(jc.perturb(delta, 1e-3, seed=seed + 2)), np.zeros(9), np.zeros(len(model.effect_names))])
    x0[delta.n_params:delta.n_params + len(frame)] = frame
    x1 = x0.copy()
    x1[model.n_geometry:] = effect_vector(model, {k: 1e-3 * v for k, v in effects.items()})  # small: every sample closes
    disp = readings(model, x1, q, cov) - readings(model, x0, q, cov)
    k = times_noise * noise * np.sqrt(3) / np.sqrt(np.mean(np.sum(disp**2, axis=1)))
    x1[model.n_geometry:] *= k
    y = add_noise("position", readings(model, x1, q, cov), noise, seed=seed + 3)
    return jc.Dataset(q=q, y=y, device="position", covariates=cov), {name: 1e-3 * v * k for name, v in effects.items()}


@pytest.mark.slow
@pytest.mark.parametrize("effects,joints", [
    ({"gap.backlash.theta2": 1.0}, ("theta2",)),
    ({"gap.drift.vx": 0.6, "gap.drift.wz": -0.8}, ()),
])
def test_injected_effect_is_diagnosed_and_recovered_on_the_delta(delta, model, effects, joints):
    data, truth = _case(delta, model, effects)
    d = jc.gap.diagnose(delta, data)
    effect = next(iter(effects)).split(".")[1]
    assert d.verdict == effect and d.joints == joints, d.report()
    assert d.shrink > 0.8, d.report()
    for name, v in truth.items():
        assert abs(d.parameters[name] - v) < 0.1 * max(abs(u) for u in truth.values()), (name, d.parameters[name], v)


@pytest.mark.slow  # ~4.5 min alone: the noise-dominated baselines choose their bias by k-fold held-out error
def test_backlash_on_a_noisy_delta_seen_from_afar_is_found(delta, model):
    """A tracker 2.6 m away turned 2 rad, 0.2 mm noise (stated), backlash at 4.5x the noise: the baselines are
    noise-dominated and biased (identify's rule), and the refit keeps that bias toward its baseline. Unbiased, the
    refit moved tool.y, dev.x or a link length 0.25-0.35 m along weakly determined directions, every fold was flagged
    as diverged and the verdict was "unexplained" (blind case 0001 of the wide generator, seed 3). Biased but run to
    convergence, fold 4's refit walked j26.d1 0.16 m in 116 steps until held-out sample 104 no longer closed (flagged
    diverged); the refits now stop after CLOSED_BASELINE_STEPS, as the baselines do (268 s alone, 2026-11-29)."""
    data, truth = _case(delta, model, {"gap.backlash.theta2": 1.0}, times_noise=4.5, n=180, seed=4, noise=2e-4,
                        frame=(1.8, -1.2, 1.4, 0.9, -1.5, 1.1))
    d = jc.gap.diagnose(delta, data, sigma_position=2e-4)
    assert d.verdict == "backlash" and d.joints == ("theta2",), d.report()
    assert d.shrink > 0.8 and not d.diverged, d.report()
    assert abs(d.parameters["gap.backlash.theta2"] / truth["gap.backlash.theta2"] - 1) < 0.1


@pytest.mark.slow
def test_thermal_on_the_delta_is_named_and_recovered(delta, model):
    """Thermal expansion is named, kappa recovered within 5 % and the gap closed. (Until the baseline started
    from the registered device frame, 3.7 cm off here, the verdict was 'unexplained': structure correlated
    with temperature was left after the refit.)"""
    data, truth = _case(delta, model, {"gap.thermal": 1.0})
    d = jc.gap.diagnose(delta, data)
    assert d.selected and d.selected[0] == ("thermal", ()), d.report()
    assert d.verdict == "thermal" and d.shrink > 0.8, d.report()
    assert abs(d.parameters["gap.thermal"] - truth["gap.thermal"]) < 0.05 * abs(truth["gap.thermal"])


@pytest.mark.slow
def test_no_effect_on_the_delta_is_none_and_smooth_joint_effects_are_absorbed(delta, model):
    """No effect: verdict none. A first-harmonic gear error of the same raw size is ~99 % absorbed by the
    Table 4.6 geometry over the 400 mm cube (what is left is below the noise): verdict none too."""
    data, _ = _case(delta, model, {"gap.gear.theta1.s1": 1.0}, times_noise=0.0)
    assert jc.gap.diagnose(delta, data).verdict == "none"
    data, _ = _case(delta, model, {"gap.gear.theta1.s1": 1.0}, times_noise=8.0, seed=3)
    d = jc.gap.diagnose(delta, data)
    assert d.verdict == "none" and d.heldout_rms_before < 1.3 * d.noise_floor, d.report()
