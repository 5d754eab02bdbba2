"""A Delta of any dimensions (issue 16, `jaxcal.robots.delta_builder`): Table 4.6 reproduced at the nominal
dimensions, and a non-nominal Delta closed by the fast path against the nominal solutions of §2.6, the
generic closure, central differences and a simulated calibration.

Each new robot compiles its closure afresh (it is a static argument): the fast test compiles only the
closure solve; the generic closure, jacfwd and the calibration are slow tests."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import core, forward_with_status
from jaxcal.closure import delta as dl
from jaxcal.robots import delta_robot
from jaxcal.robots.builtin import _data_file, free_list
from jaxcal.robots.io import load_robot

# rb, rn, n, m of the issue; arms at 10, 130, 250 deg; a narrower parallelogram and an offset tool
OTHER = dl.DeltaGeometry(rb=0.15, rn=0.05, n=0.3, m=0.7, psi=tuple(np.deg2rad([10.0, 130.0, 250.0])), spread=0.04,
                         tool=(0.01, -0.02, -0.05))


@pytest.fixture(scope="module")
def other():
    return delta_robot(OTHER, name="other_delta")


def _settings(n, seed):
    return np.random.default_rng(seed).uniform(-0.1, 1.3, (n, 3))


def _wrap(x):
    return np.angle(np.exp(1j * np.asarray(x)))


def test_nominal_geometry_reproduces_table_4_6():
    """Same bodies, closures, free marks, home and limits as delta.yaml; parameters equal to Table 4.6's
    4 printed digits (max difference 4.1e-5 m, nacelle point j12.d1) and to `full_precision_nominal` to
    4.4e-16 (the a2 = 2 pi / 3 of rows 3-4, one ulp)."""
    table = load_robot(_data_file("delta.yaml"))
    rb = delta_robot()
    assert rb.names == table.names and rb.bodies == table.bodies and rb.tip == table.tip
    assert rb.closure.pairs == dl.PAIRS and rb.closure.free == dl.FREE and rb.closure.geometry == dl.NOMINAL
    assert list(np.array(rb.names)[rb.free_mask]) == free_list("delta.yaml")
    assert rb.joint_names == ("theta1", "theta2", "theta3")
    np.testing.assert_array_equal(rb.home_np, [0.5] * 3)
    np.testing.assert_array_equal(np.stack([rb.q_min, rb.q_max]), [[-0.2] * 3, [1.4] * 3])
    diff = np.abs(rb.nominal_np - table.nominal_np)
    assert diff.max() < 5e-5, (diff.max(), rb.names[diff.argmax()])
    printed = np.array([not n.startswith(("j10.", "j11.", "j12.", "j13.", "j14.")) for n in rb.names])
    assert diff[printed].max() < 1e-15, diff[printed].max()
    exact = np.abs(rb.nominal_np - np.asarray(dl.full_precision_nominal(table)))
    assert exact.max() < 1e-12, exact.max()


def test_invalid_dimensions_are_refused_with_a_reason():
    with pytest.raises(ValueError, match="n must be a positive length"):
        dl.DeltaGeometry(n=0.0)
    with pytest.raises(ValueError, match="psi must be 3 finite numbers"):
        dl.DeltaGeometry(psi=(0.0, 2.0))
    with pytest.raises(ValueError, match="must be distinct"):
        dl.DeltaGeometry(psi=(0.0, 2 * np.pi, 2.0))
    with pytest.raises(ValueError, match="tool must be 3"):
        dl.DeltaGeometry(tool=(0.0, 0.0))
    with pytest.raises(ValueError, match="do not reach the nacelle"):
        delta_robot(dl.DeltaGeometry(m=0.5))  # at theta = -0.2 the shifted elbows are 0.67 m off the axis
    with pytest.raises(ValueError, match="q_min <= home <= q_max"):
        delta_robot(home=(2.0, 0.5, 0.5))
    with pytest.raises(ValueError, match="no parameters"):
        delta_robot(free=["j99.d1"])


def test_other_geometry_closes_on_its_nominal_solutions(other):
    """Tool = nominal direct solution of these dimensions + tool offset (the nacelle parallel to the base),
    inverse(forward) = the settings; the fast path serves every sample (Newton only, no continuation). The tool
    comes from `forward_with_status` (the closure solve, then the open tree at its free joints), which
    `jc.simulate` uses."""
    assert other.closure.geometry == OTHER
    theta = _settings(3, seed=1)
    sol = dl.solve(other, other.nominal, theta)
    assert np.all(np.asarray(sol.status) == dl.CLOSED) and np.all(np.asarray(sol.steps) <= dl.NEWTON_STEPS), sol
    pose, status = forward_with_status(other, other.nominal, theta)
    np.testing.assert_array_equal(status, sol.status)
    for k, t in enumerate(theta):
        P, ok = dl.direct(t, OTHER)
        assert bool(ok)
        assert float(jnp.max(jnp.abs(pose.p[k] - P - jnp.asarray(OTHER.tool)))) < 1e-9
        assert float(jnp.max(jnp.abs(pose.R[k] - dl.R_NACELLE))) < 1e-9
        back, ok = dl.inverse(pose.p[k] - jnp.asarray(OTHER.tool), OTHER)
        assert bool(ok) and float(jnp.max(jnp.abs(back - t))) < 1e-9


@pytest.mark.slow  # compiles the generic whole-tree closure
def test_fast_path_agrees_with_the_generic_closure(other):
    """`jaxcal.closure.core.solve` (whole-tree closure, damped Newton from the closed home configuration)
    and the fast path give the same 15 free joints at perturbed parameters."""
    a = jc.perturb(other, 1e-3, seed=2)
    for theta in _settings(2, seed=3):  # both solves are kept executables (`jaxcal.exported`): compiled, not op by op
        fast = dl.solve(other, a, theta)
        generic = core.solve(other, a, theta, start=other.closure.start)
        assert bool(fast.ok) and bool(generic.ok)
        assert float(np.max(np.abs(_wrap(fast.theta_free - generic.theta_free)))) < 1e-9


@pytest.mark.slow  # compiles jacfwd through the closure (~15-25 s)
def test_jacobian_through_the_closure_matches_central_differences(other):
    """jacfwd of the tool positions w.r.t. the 74 free parameters (implicit function theorem) vs central
    differences, h = 1e-6, float64, at perturbed parameters and 4 settings."""
    free = np.flatnonzero(other.free_mask)
    a0 = jc.perturb(other, 1e-3, seed=5)
    q = jnp.asarray(_settings(4, seed=7))

    def tool(x):
        p = jc.forward(other, a0.at[free].set(x), q).p.ravel()
        return p, p

    both = jax.jit(jax.jacfwd(tool, has_aux=True))  # one compile gives the Jacobian and the positions
    J, _ = both(a0[free])
    rel = rel_err(J, central_fd(lambda x: both(jnp.asarray(x))[1], a0[free], h=1e-6))
    assert rel < 1e-6, f"jacfwd vs central differences: relative error {rel:.2e}"


@pytest.mark.slow  # a calibration of the 30-body closed model (compile-bound, ~1-2 min)
def test_simulated_calibration_recovers_the_robot(other):
    """Free parameters off by ~1 mm / 1 mrad, position device (frame and marker unknown), 60 noise-free
    settings: the calibrated model predicts 40 new settings to < 0.01 mm."""
    a_true = jc.perturb(other, 1e-3, seed=11)
    fit = jc.identify(other, jc.simulate(other, a_true, _settings(60, seed=12), "position"))
    pe, _ = fit.errors(jc.simulate(other, a_true, _settings(40, seed=13), "position"))
    assert float(np.max(pe)) < 1e-5, f"held-out position error {np.max(pe) * 1e3:.2e} mm"
