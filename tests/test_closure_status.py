"""Closure status per sample, the penalty pose of unclosed samples for every device kind, the warning at
simulate and the re-check at the solution of a fit (issue 16 items 1-2)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import CLOSED, UNCLOSED, closure_status
from jaxcal.closure import delta as dl
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.robots.builtin import FOURBAR3D_TABLE_4_2B

Q = jnp.array([[0.3], [1.5], [-0.8]])  # theta1 = 1.5 closes for the nominal 3-D four-bar, not for Table 4.2b


@pytest.fixture(scope="module")
def fb3():
    return jc.robots.get("fourbar3d")


def _table_4_2b(rb):
    vals = {f"j{i}.{f}": v for i, row in enumerate(FOURBAR3D_TABLE_4_2B, 1) for f, v in zip(("a1", "a2", "a3", "d1", "d2", "d3"), row)}
    return jnp.array([vals[n] for n in rb.names])


def test_status_names_the_unclosed_sample(fb3):
    assert np.asarray(closure_status(fb3, fb3.nominal, Q)).tolist() == [CLOSED] * 3
    assert np.asarray(closure_status(fb3, _table_4_2b(fb3), Q)).tolist() == [CLOSED, UNCLOSED, CLOSED]


def test_unclosed_sample_is_penalised_for_an_orientation_device(fb3):
    """An orientation-only device: the unclosed sample's error is the penalty rotation (120 degrees), not the
    orientation of an unconverged configuration; the closed samples keep their exact readings."""
    data = jc.simulate(fb3, fb3.nominal, Q, "orientation")
    dev = data.device
    x_bad = jnp.concatenate([_table_4_2b(fb3), dev.nominal])
    _, oe = dev.split_errors(residuals(fb3, dev, x_bad, Q, jnp.asarray(data.y), residual_weights(dev, 1.0, 1.0)))
    oe = np.asarray(oe)
    assert oe[1] > 1.0, oe  # rad


def test_simulate_warns_about_unclosed_samples(fb3):
    with pytest.warns(UserWarning, match=r"1 of 3 simulated sample\(s\) do not close \(1 unclosed\): \[1\]"):
        jc.simulate(fb3, _table_4_2b(fb3), Q, "position")


@pytest.mark.slow  # ~160 s on the loaded 2-core machine (compile of jacfwd through the Delta's two paths)
def test_delta_general_path_closes_what_the_fast_path_misses_and_differentiates():
    """Delta with 1 cm / 0.01 rad errors: settings the fast Newton does not close on the nominal branch
    are closed by the continuation; jacfwd of the tool position w.r.t. the free parameters through those
    samples matches central differences (h = 1e-6): relative error < 1e-6."""
    rb = jc.robots.get("delta")
    a = jc.perturb(rb, 1e-2, seed=1)
    P = dl.grid()[0] - 0.1 + 0.6 * np.random.default_rng(3).random((400, 3))
    q, ok = jax.jit(jax.vmap(dl.inverse))(jnp.asarray(P))
    q = np.asarray(q)[np.asarray(ok)]
    fast = jax.jit(jax.vmap(lambda qi: dl._fast_single(rb, a, qi)[2]))(jnp.asarray(q))
    sol = dl.solve(rb, a, q)
    missed = np.flatnonzero(~np.asarray(fast) & np.asarray(sol.ok))
    assert missed.size >= 1, "no setting needed the general path: draw more"
    qs = jnp.asarray(q[missed[:4]])
    free = np.flatnonzero(rb.free_mask)
    f = lambda x: jc.forward(rb, a.at[free].set(x), qs).p.ravel()  # noqa: E731
    J = jax.jacfwd(f)(a[free])
    err = rel_err(J, central_fd(f, a[free], h=1e-6))
    assert err < 1e-6, err


def test_solvers_that_need_reverse_mode_are_refused_on_the_generic_closure(fb3):
    """Dogleg and BFGS transpose the Jacobian; the generic closure's custom JVP cannot be transposed (it raised an
    AssertionError deep in JAX): identify says so and names the solvers that work."""
    data = jc.simulate(fb3, fb3.nominal, jc.random_configurations(fb3, 12, seed=1), "position")
    for solver in ("dogleg", "bfgs"):
        with pytest.raises(ValueError, match="reverse-mode"):
            jc.identify(fb3, data, solver=solver)
