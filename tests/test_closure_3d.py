"""The 3-D four-bar of seed 004 Table 4.2a: closure, closed-loop Jacobian three ways, identification."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import FAIL_OFFSET, closed, closure_residual, solve, tree_frames
from jaxcal.robots.builtin import FOURBAR3D_TABLE_4_2B

FREE_OFFSETS = ("j3.a3", "j4.a3", "j5.a3")  # a3 of the free joints: the joint variables themselves


@pytest.fixture(scope="module")
def fb3():
    return jc.robots.get("fourbar3d")


def table_4_2b(rb):
    vals = {f"j{i}.{f}": v for i, row in enumerate(FOURBAR3D_TABLE_4_2B, 1) for f, v in zip(("a1", "a2", "a3", "d1", "d2", "d3"), row)}
    return jnp.array([vals[n] for n in rb.names])


def test_structure_and_closure(fb3):
    """31 parameters (26 of the thesis plus the a3 of joints 2-6, which it leaves out), free joints 3-5."""
    assert fb3.n_params == 31 and fb3.n_inputs == 1
    assert fb3.closure.pairs == ((2, 6, "position"),) and fb3.closure.free == (3, 4, 5)
    a = table_4_2b(fb3)
    q = jnp.array([[0.3], [-1.0], [1.1]])
    sol = solve(fb3, a, q)
    assert bool(jnp.all(sol.ok)) and float(jnp.max(sol.residual_norm)) < 1e-12
    for qi, th in zip(q, sol.theta_free):
        f = tree_frames(fb3, a, qi, th)
        assert float(jnp.linalg.norm(f.p[1] - f.p[5])) < 1e-12  # ball joint: frames 2 and 6 meet
    p_tree = jax.vmap(lambda qi, th: tree_frames(fb3, a, qi, th).p[4])(q, sol.theta_free)
    np.testing.assert_allclose(np.asarray(jc.forward(fb3, a, q).p), np.asarray(p_tree), atol=1e-12)


def _parts(rb, a, q):
    th = solve(rb, a, q).theta_free
    f = lambda a_, t: tree_frames(rb, a_, q, t).p[rb.tip]  # noqa: E731
    v = lambda a_, t: closure_residual(rb, a_, q, t)  # noqa: E731
    return [np.asarray(jax.jit(jax.jacfwd(g, k))(a, th)) for g in (f, v) for k in (0, 1)]  # compiled whole


@pytest.mark.parametrize("theta1", [0.3, -0.9])
def test_closed_loop_jacobian_three_ways(fb3, theta1):
    """jacfwd through the closure = chain rule (eq 2.69) = null space (eq 2.88-2.97) = central FD."""
    a = table_4_2b(fb3)
    q = jnp.array([theta1])
    J = np.asarray(jax.jacfwd(lambda a_: jc.forward(fb3, a_, q).p)(a))

    fa, ft, va, vt = _parts(fb3, a, q)
    J_chain = fa - ft @ np.linalg.solve(vt, va)  # v: 3 position rows, 3 free joints
    assert rel_err(J, J_chain) < 1e-12

    # null space over all parameters, the free joints' a3 standing for their joint variables
    free = [fb3.names.index(n) for n in FREE_OFFSETS]
    controlled = [i for i in range(fb3.n_params) if i not in free]
    np.testing.assert_allclose(va[:, free], vt, atol=1e-14)  # d v/d a3_j == d v/d theta_j
    _, s, Vt = np.linalg.svd(va)
    r = int(np.sum(s > 1e-10 * s[0]))
    assert r == 3
    N = Vt[r:].T
    J_null = np.zeros_like(J)
    J_null[:, controlled] = fa @ (N @ np.linalg.inv(N[controlled]))
    assert rel_err(J, J_null) < 1e-10
    assert np.abs(J[:, free]).max() < 1e-12  # a free joint's offset is absorbed by the closure

    J_fd = central_fd(lambda x: jc.forward(fb3, jnp.asarray(x), q).p, np.asarray(a), h=1e-6)
    assert rel_err(J, J_fd) < 1e-8


def test_newton_hybrid_matches_lm(fb3):
    rb = fb3.replace(closure=dataclasses.replace(fb3.closure, solver="newton"))
    a = table_4_2b(fb3)
    q = jnp.asarray(jc.random_configurations(fb3, 16, seed=3))
    s_lm, s_nw = solve(fb3, a, q), solve(rb, a, q)
    assert bool(jnp.all(s_lm.ok)) and bool(jnp.all(s_nw.ok))
    np.testing.assert_allclose(np.asarray(s_nw.theta_free), np.asarray(s_lm.theta_free), atol=1e-10)
    assert int(jnp.max(s_nw.steps)) < int(jnp.max(s_lm.steps))


def test_infeasible_sample_is_finite_and_costly(fb3):
    """A geometry at which a sample cannot close: finite readings and Jacobian, a cost far above any
    feasible one, so LM's trust region / BFGS' line search rejects the step (seed 004 §3.3)."""
    from jaxcal.fit.identify import residual_weights, residuals

    q = jnp.array([[0.3], [1.5], [-0.8]])
    a_good = fb3.nominal
    a_bad = table_4_2b(fb3)  # theta1 = 1.5 closes for the nominal geometry, not for Table 4.2b
    assert closed(fb3, a_good, q).tolist() == [True, True, True]
    assert closed(fb3, a_bad, q).tolist() == [True, False, True]
    data = jc.simulate(fb3, a_good, q, "position")
    dev = data.device
    w = residual_weights(dev)
    x_good, x_bad = (jnp.concatenate([a, dev.nominal]) for a in (a_good, a_bad))
    r_bad = residuals(fb3, dev, x_bad, q, jnp.asarray(data.y), w)
    J_bad = jax.jacfwd(lambda x: residuals(fb3, dev, x, q, jnp.asarray(data.y), w))(x_bad)
    assert bool(jnp.all(jnp.isfinite(r_bad))) and bool(jnp.all(jnp.isfinite(J_bad)))
    assert float(jnp.min(jnp.abs(r_bad[1]))) > 0.5 * FAIL_OFFSET / 1e-3
    assert float(jnp.abs(J_bad[1, :, :fb3.n_params]).max()) == 0.0  # no robot gradient towards a fake optimum
    assert float(jnp.abs(residuals(fb3, dev, x_good, q, jnp.asarray(data.y), w)).max()) < 1e-9


@pytest.mark.slow
def test_identify_through_closure(fb3):
    """Noise-free position data: jc.identify recovers the perturbed identifiable parameters.

    The perturbation is Table 4.2b restricted to the base set jc.identify estimates (the other Table
    4.2b entries are not identifiable from frame-5 positions; left in, they are absorbed and leave a
    ~0.08 mm residual through the nonlinearity of the regrouping). The data include theta1 = 1.45,
    near the stretched singularity at pi/2.
    """
    Q = np.concatenate([jc.random_configurations(fb3, 30, seed=1), [[1.45]]])
    probe = jc.identify(fb3, jc.simulate(fb3, fb3.nominal, Q, "position"), known=("dev", "tool"))
    est = [fb3.names.index(n) for n in probe.estimated]
    a_true = np.array(fb3.nominal)
    a_true[est] = np.asarray(table_4_2b(fb3))[est]
    assert bool(jnp.all(closed(fb3, a_true, Q))) and bool(jnp.all(closed(fb3, fb3.nominal, Q)))
    fit = jc.identify(fb3, jc.simulate(fb3, a_true, Q, "position"), known=("dev", "tool"))
    assert fit.estimated == probe.estimated
    assert fit.rms_before > 1.0 and fit.rms_after < 1e-7  # mm
    np.testing.assert_allclose(np.asarray(fit.a), a_true, atol=1e-9)


def test_yaml_round_trip_and_bad_closure_column(fb3, tmp_path):
    path = tmp_path / "fb3.yaml"
    jc.save_robot(fb3, str(path))
    back = jc.load_robot(str(path))
    assert back.closure == fb3.closure and back.names == fb3.names
    np.testing.assert_array_equal(back.nominal_np, fb3.nominal_np)
    text = path.read_text().replace("[-1.5707963267948966, 0.0, 0.0, -1.0, 0.0, 0.0, 5, 2, 2]",
                                    "[-1.5707963267948966, 0.0, 0.0, -1.0, 0.0, 0.0, 5, 9, 2]")
    assert "5, 9, 2" in text
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(jc.robots.RobotFileError, match=r"bad.yaml.*row 6: field 'closure' = 9 must name another row"):
        jc.load_robot(str(bad))


def test_identify_leaves_out_samples_that_do_not_close_at_the_start(fb3):
    """Samples that do not close at the starting geometry are dropped with a warning naming them
    (not allowed to dominate the residual scale and stall the fit) and reported in `info`."""
    q = jnp.array([[0.3], [1.5], [-0.8], [0.6]])
    data = jc.simulate(fb3, fb3.nominal, q, "position")
    with pytest.warns(UserWarning, match=r"do not close.*\[1\]"):
        fit = jc.identify(fb3, data, a0=table_4_2b(fb3), known=("dev", "tool"), free=["j1.d1", "j3.d1"])
    assert fit.info["unclosed_samples"] == (1,) and fit.info["n_samples"] == 3
    assert np.isfinite(fit.rms_after) and fit.rms_after < fit.rms_before


@pytest.mark.slow
def test_all_of_table_4_2b_is_fitted_through_the_final_stage(fb3):
    """Noise-free positions of the 3-D four-bar with every Table 4.2b error (not only the base set's): the base set
    chosen at the nominal leaves a systematic residual, and parameters whose columns are zero at the nominal have
    an effect at the solution. The final all-parameter stage adds those too (9 parameters instead of 4): RMS
    0.0028 mm left instead of 0.045 mm (measured; from 13.75 mm with the frames fitted)."""
    Q = np.concatenate([jc.random_configurations(fb3, 30, seed=1), [[1.45]]])
    fit = jc.identify(fb3, jc.simulate(fb3, np.asarray(table_4_2b(fb3)), Q, "position"), known=("dev", "tool"))
    assert fit.polished and fit.info["polish"]["added"] == 9
    assert fit.rms_after < 0.005


def test_fit_jacobian_in_reverse_mode_matches_forward_mode_and_central_differences(fb3):
    """The fits' Jacobian through the generic closure (`core.data_residual_and_jacobian`: `presolve` for the batch,
    then reverse mode sample by sample through `forward_presolved`'s implicit step) against forward mode through
    `forward_closed`'s custom JVP on every sample, and against central differences (h = 1e-6) of the residuals
    re-solving the closure on the samples that close. theta1 = 1.45 does not close at these parameters."""
    from jaxcal.fit import core

    a0 = jc.perturb(fb3, 1e-3, seed=1)
    q = jnp.asarray(np.concatenate([jc.random_configurations(fb3, 11, seed=1), [[1.45]]]))
    ok = np.asarray(closed(fb3, a0, q))
    assert ok[:-1].all() and not ok[-1]
    model = core.RobotDevice(fb3, jc.measure.devices.as_device("position"))
    a_full = jnp.concatenate([a0, model.device.nominal])
    y = jnp.asarray(core.predicted(fb3, model.device, a_full, q)) + 1e-4
    cov, w = jnp.zeros((len(q), 0)), jnp.ones((len(q), 3))
    r, J = jax.jit(lambda a: core.data_residual_and_jacobian(model, a, q, y, cov, w))(a_full)
    fn = lambda b, _: model.residuals(b, q, y, cov, w).reshape(-1)  # noqa: E731
    r_fwd, J_fwd = jax.jit(lambda a: core.residual_and_jacobian(fn, a, None))(a_full)
    np.testing.assert_allclose(r, r_fwd, rtol=0, atol=1e-15)
    assert rel_err(J, J_fwd) < 1e-12, rel_err(J, J_fwd)  # measured 8.6e-17

    rows = np.repeat(ok, 3)
    res = jax.jit(lambda a: model.residuals(a, q, y, cov, w).reshape(-1))
    fd = central_fd(lambda a: np.asarray(res(a))[rows], np.asarray(a_full), h=1e-6)
    err = rel_err(np.asarray(J)[rows], fd)
    assert err < 1e-6, err  # measured 1.7e-10
    assert np.all(np.asarray(J)[~rows][:, : fb3.n_params] == 0.0)  # the device's columns move the penalty reading
