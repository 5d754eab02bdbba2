"""The Delta robot (seed 004 §2.6, Table 4.6): nominal direct/inverse solutions, the closed
MCPC model against them, closure flags and derivatives through the closure."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import delta as dl
from jaxcal.closure.core import FAIL_OFFSET, tree_frames
from jaxcal.fit import core

N = 16  # one batch shape for every closure call: one compile per function
_direct = jax.jit(jax.vmap(dl.direct))
_inverse = jax.jit(jax.vmap(dl.inverse))


@pytest.fixture(scope="module")
def rb():
    return jc.robots.get("delta")


def _workspace(n, seed=0):
    """Actuator settings whose nacelle centre lies in the 400 mm grid cube (inverse of random points)."""
    P = dl.grid()[0] + 0.4 * np.random.default_rng(seed).random((n, 3))
    theta, ok = _inverse(jnp.asarray(P))
    assert bool(jnp.all(ok))
    return P, theta


def test_inverse_of_direct_is_identity():
    theta = jnp.asarray(np.random.default_rng(1).uniform(-0.1, 1.3, (500, 3)))
    P, ok = _direct(theta)
    back, ok2 = _inverse(P)
    assert bool(jnp.all(ok)) and bool(jnp.all(ok2))
    assert float(jnp.max(jnp.abs(back - theta))) < 1e-12


def test_direct_of_inverse_on_grid():
    P = jnp.asarray(dl.grid())
    theta, ok = _inverse(P)
    again, ok2 = _direct(theta)
    assert bool(jnp.all(ok)) and bool(jnp.all(ok2))
    assert float(jnp.max(jnp.abs(again - P))) < 1e-12
    # every rod has length m: |B_i - rn radial_i - P| = m
    B = jax.jit(jax.vmap(dl.elbows))(theta) - 0.196 * dl._radial(jnp.asarray(dl.NOMINAL.psi))
    assert float(jnp.max(jnp.abs(jnp.linalg.norm(B - P[:, None, :], axis=-1) - 0.9))) < 1e-12


def test_unreachable_point_is_flagged():
    _, ok = dl.inverse(jnp.array([0.0, 0.0, -2.0]))  # below the reach n + m
    assert not bool(ok)
    P, ok = dl.direct(jnp.array([0.0, 0.0, 0.0]))  # arms horizontal: rods at radius rb + n - rn
    assert bool(ok) and abs(float(P[2]) + np.sqrt(0.9**2 - (0.2805 + 0.6 - 0.196) ** 2)) < 1e-12


def test_closed_mcpc_delta_agrees_with_direct_solution(rb):
    """jc.forward closes the 30-body tree; the tool (nacelle centre) must match eq 2.135-2.146.
    With Table 4.6's 4-digit nacelle coordinates the models differ by up to ~4e-5 m; with the
    coordinates at full precision they agree to 1e-12 m."""
    _, theta = _workspace(N)
    P, _ = _direct(theta)
    pose = jc.forward(rb, rb.nominal, theta)
    assert bool(jnp.all(dl.closed(rb, rb.nominal, theta)))
    assert float(jnp.max(jnp.abs(pose.p - P))) < 5e-5
    exact = jc.forward(rb, dl.full_precision_nominal(rb), theta)
    assert float(jnp.max(jnp.abs(exact.p - P))) < 1e-12
    # the nacelle stays parallel to the base (R = Rz(-pi/2) of the nacelle frame)
    assert float(jnp.max(jnp.abs(exact.R - dl.R_NACELLE))) < 1e-10


def test_closure_holds_on_the_whole_tree_for_perturbed_geometry(rb):
    """The reduced 5 x 5 system closes all 15 closure equations of the tree (checked body by body),
    the reported residual norm equals the whole-tree one, and jc.forward's tool is the whole tree's at those joints."""
    a = jc.perturb(rb, 2e-3, seed=3)
    _, theta = _workspace(N, seed=2)
    sol = dl.solve(rb, a, theta)
    assert sol.theta_free.shape == (N, 15) and bool(jnp.all(sol.ok))
    tree_tool = jax.jit(jax.vmap(lambda qi, th: tree_frames(rb, a, qi, th).p[rb.tip]))(theta, sol.theta_free)
    np.testing.assert_allclose(jc.forward(rb, a, theta).p, tree_tool, rtol=0, atol=1e-12)
    st = dl._statics(rb, a)
    for q, th in zip(theta[:3], sol.theta_free[:3]):
        fixed = dl._fixed(rb, st, q)
        nacelle = dl._nacelle(rb, st, fixed, th[:5])
        rods = th[5:].reshape(5, 2).T
        assert float(dl.closure_error(rb, st, q, nacelle, rods)) < 1e-12


def test_geometric_newton_jacobian_matches_jacfwd(rb):
    a = jc.perturb(rb, 2e-3, seed=4)
    st = dl._statics(rb, a)
    q = jnp.array([0.3, 0.5, 0.7])
    fixed = dl._fixed(rb, st, q)
    x = jnp.array([1.8, -0.1, 0.1, 0.7, 0.01])
    _, J = dl._residual_and_jacobian(rb, st, fixed, x)
    J_ad = jax.jacfwd(functools.partial(dl._sphere_residual, rb, st, fixed))(x)
    assert float(jnp.max(jnp.abs(J - J_ad))) < 1e-12


def test_newton_state_carries_the_residual_and_direction_of_its_point(rb):
    """`dl._newton_turn` evaluates one point a turn and keeps the F and Newton direction of the point it takes: after
    full steps and after halved ones (the gimbal-lock setting of the test below, from its start) the state's F and
    d are those at its x, a point is counted only when taken, a rejected trial halves t and keeps x. The Newton it
    drives reaches max |F| <= NEWTON_TOL there."""
    a = jc.perturb(rb, 1e-3, seed=1)
    q = jnp.asarray(jc.random_configurations(rb, 125, seed=2))[35]
    qj = dl.joint_variables(rb, a, q)
    st = dl._statics(rb, a)
    fixed = dl._fixed(rb, st, qj)
    x0, _ = dl._start(rb, st, qj, fixed)
    turn = jax.jit(lambda s: dl._newton_turn(rb, st, fixed, s))
    s = turn(dl._newton_start(x0))
    np.testing.assert_array_equal(s.x, x0)
    halvings = taken = 0
    while bool(dl._newton_more(s)):
        new = turn(s)
        if bool(new.halving):  # the trial did not lower |F|: x kept, t halved, nothing counted
            halvings += 1
            np.testing.assert_array_equal(new.x, s.x)
            assert float(new.t) == 0.5 * float(s.t) and int(new.evals) == int(s.evals)
        else:
            taken += 1
            np.testing.assert_allclose(new.x, s.x - s.t * s.d, rtol=0, atol=1e-15)
            assert float(new.t) == 1.0 and int(new.evals) == int(s.evals) + 1
        F, J = dl._residual_and_jacobian(rb, st, fixed, new.x)
        np.testing.assert_allclose(new.F, F, rtol=0, atol=1e-15)
        np.testing.assert_allclose(new.d, dl.solve_small(J, F), rtol=1e-12, atol=1e-15)
        s = new
    assert halvings > 0 and taken > 0, "no step was cut: the start is inside Newton's basin"
    x, err, evals = jax.jit(lambda x0: dl._newton(rb, st, fixed, x0))(x0)
    assert float(err) <= dl.NEWTON_TOL and int(evals) <= dl.NEWTON_STEPS, (err, evals)
    np.testing.assert_array_equal(x, s.x)


def test_turned_nacelle_is_the_chain_at_the_turned_joints_to_first_order(rb):
    """`dl._turned` (the nacelle after rod 1's joints turn by dx, from the frames at x) against the chain evaluated
    at x + dx: for dx ~ 1e-6 rad the two agree to second order (~1e-12) while the nacelle itself moves by ~1e-6."""
    a = jc.perturb(rb, 1e-3, seed=1)
    q = jnp.asarray(jc.random_configurations(rb, 4, seed=5))
    dxs = 1e-6 * np.random.default_rng(0).standard_normal((4, 5))
    for qi, dx in zip(q, dxs):
        qj = dl.joint_variables(rb, a, qi)
        st = dl._statics(rb, a)
        fixed = dl._fixed(rb, st, qj)
        x = dl._newton(rb, st, fixed, dl._start(rb, st, qj, fixed)[0])[0]
        at_x = dl._nacelle(rb, st, fixed, x)
        turned = dl._turned(at_x, dl._chain(st, fixed["arm1"], dl.ROD1, x), jnp.asarray(dx))
        moved = dl._nacelle(rb, st, fixed, x + dx)
        assert float(jnp.max(jnp.abs(moved.p - at_x.p))) > 1e-8  # the turn is not negligible at this size
        assert float(jnp.max(jnp.abs(turned.p - moved.p))) < 1e-11
        assert float(jnp.max(jnp.abs(turned.R - moved.R))) < 1e-11


def test_infeasible_geometry_is_flagged_and_finite(rb):
    """A rod of 0.2 m cannot reach the nacelle: every sample is flagged, the pose stays finite and
    carries FAIL_OFFSET (so a fit step into such a geometry is rejected)."""
    _, q = _workspace(N, seed=6)
    assert bool(jnp.all(dl.closed(rb, rb.nominal, q)))
    bad = rb.nominal.at[rb.index("j17.d1")].set(0.2)
    assert not bool(jnp.any(dl.closed(rb, bad, q)))
    p = jc.forward(rb, bad, q).p
    assert bool(jnp.all(jnp.isfinite(p))) and float(jnp.min(p)) > 100.0
    # the penalty stays FAIL_OFFSET from a pose within the robot's reach (measured 1.1 m; 21 m when the unclosed
    # samples' nacelle was turned to first order by their Newton step, as the closed ones' is)
    assert float(jnp.max(jnp.abs(p - FAIL_OFFSET))) < 3.0


def test_closed_loop_jacobian_matches_central_differences(rb):
    """jacfwd of the tool pose w.r.t. the 74 free parameters through the closure (implicit
    function theorem) vs central differences, h = 1e-6: relative error < 1e-6."""
    a0 = jc.perturb(rb, 1e-3, seed=5)
    _, q = _workspace(N, seed=7)
    free = np.flatnonzero(rb.free_mask)

    def f(x):
        pose = jc.forward(rb, a0.at[free].set(x), q)
        return jnp.concatenate([pose.p.ravel(), pose.R.ravel()])

    x0 = a0[free]
    J = jax.jacfwd(f)(x0)
    rel = rel_err(J, central_fd(f, x0, h=1e-6))
    assert rel < 1e-6, rel
    # d/dq through the closure is exercised by the compensation test (Newton converges to 1e-12 m)


def test_compensation_refuses_targets_of_the_wrong_shape(rb):
    from jaxcal.fit.compensate import compensate

    with pytest.raises(ValueError, match="targets must be"):
        compensate(rb, rb.nominal, jnp.zeros((4, 2)), start=jnp.zeros((4, 3)))


@pytest.mark.slow  # a study: 125 targets through the closure's Jacobian (compile-bound, ~45-90 s)
def test_compensation_on_the_grid(rb):
    """§3.2/§4.4: commanding the nominal inverse solution on the 125-point grid with the rod of
    frame 26 20 mm longer misses by millimetres; compensating with the (here exactly) calibrated
    model puts the tool on every grid point to < 1e-9 m."""
    from jaxcal.fit.compensate import compensate

    a_true = rb.nominal.at[rb.index("j26.d1")].add(0.02)
    P = jnp.asarray(dl.grid())
    q_nominal, _ = _inverse(P)
    before = jnp.linalg.norm(jc.forward(rb, a_true, q_nominal).p - P, axis=-1)
    comp = compensate(rb, a_true, P, start=q_nominal)
    after = jnp.linalg.norm(jc.forward(rb, a_true, comp.q).p - P, axis=-1)
    assert bool(jnp.all(comp.ok))
    assert float(jnp.max(before)) > 5e-3 and float(jnp.max(after)) < 1e-9
    with pytest.raises(ValueError, match="targets must be"):
        compensate(rb, a_true, P[:, :2], start=q_nominal)


def test_broken_reduction_hands_over_to_the_generic_closure(rb):
    """Issue 16 item 3: a fixed entry the fast path relies on (j16.a1, a universal joint's right angle) moved
    by 1 mrad made the fast path flag every sample although the whole tree still closes. Such a robot, and a
    fit that frees such an entry, are served by the generic whole-tree closure, with a warning naming it."""
    a = np.asarray(rb.nominal).copy()
    assert dl.reduction_breaks(rb, a) == [] and rb.closure.serving(rb, a) is rb
    a[rb.index("j16.a1")] += 1e-3
    with pytest.warns(UserWarning, match="j16.a1"):
        served = rb.closure.serving(rb, a)
    assert type(served.closure) is jc.closure.Closure and served.closure.free == rb.closure.free
    # one serving robot per Delta: compiled closures take the robot as a static argument (hashed by identity), and
    # a new object per call compiled the generic closure again at every evaluation (~30 s each)
    with pytest.warns(UserWarning, match="j16.a1"):
        assert rb.closure.serving(rb, a + 1e-9) is served
    free = rb.free_mask.copy()
    free[rb.index("j19.d1")] = True
    assert dl.reduction_breaks(rb, rb.nominal, free) == ["j19.d1"]
    dev = jc.make_device("position")
    with pytest.warns(UserWarning, match="j19.d1"):
        problem = core.make_problem(rb, dev, np.zeros((2, 3)), np.zeros((2, 3)), weights=np.ones(3),
                                    free=np.concatenate([free, np.zeros(len(dev.names), bool)]),
                                    a_ref=np.concatenate([rb.nominal, dev.nominal]))
    assert type(problem.robot.closure) is jc.closure.Closure
    plain = core.make_problem(rb, dev, np.zeros((2, 3)), np.zeros((2, 3)), weights=np.ones(3),
                              free=np.concatenate([rb.free_mask, np.zeros(len(dev.names), bool)]),
                              a_ref=np.concatenate([rb.nominal, dev.nominal]))
    assert plain.robot is rb


@pytest.mark.slow  # compiles the generic closure of the 30-body tree, then a fit through it
def test_a_delta_with_a_bent_universal_joint_closes_and_is_calibrated(rb):
    """j16.a1 1 mrad off its right angle: every sample closes (the fast path flagged all 27 unclosed). A fit that
    frees j16.a1 with the six rod lengths finds rod 26's 2 mm from noise-free positions and leaves j16.a1 out of
    the base set: a universal joint's rod end sweeps the same sphere whatever the angle between its axes, so the
    angle has no effect on the tool (with base=False all seven are estimated at condition ~1e16)."""
    theta = np.asarray(jax.vmap(dl.inverse)(jnp.asarray(dl.grid(spacing=0.2, n=3)))[0])
    a_true = rb.nominal.at[rb.index("j16.a1")].add(1e-3).at[rb.index("j26.d1")].add(2e-3)
    assert not np.any(np.asarray(dl.solve(rb, a_true, theta).ok))  # the fast path alone
    with pytest.warns(UserWarning, match="j16.a1"):
        status = np.asarray(jc.closure.closure_status(rb, a_true, theta))
    assert np.all(status == jc.closure.CLOSED), status
    with pytest.warns(UserWarning, match="j16.a1"):
        data = jc.simulate(rb, a_true, theta, "position")
    free = ["j16.a1", "j7.d1", "j17.d1", "j20.d1", "j23.d1", "j26.d1", "j29.d1"]
    with pytest.warns(UserWarning, match="j16.a1"):
        fit = jc.identify(rb, data, free=free, known=("dev", "tool"))
    assert "j16.a1" not in fit.estimated and set(fit.estimated) == set(free[1:]), fit.estimated
    err = np.abs(np.asarray(fit.a) - np.asarray(a_true))[[rb.index(n) for n in free[1:]]]
    assert fit.converged and err.max() < 1e-7, (fit.converged, err.max())  # measured 3.0e-8 m


@pytest.mark.parametrize("needing", [0, 1, dl.TRACKED_CHUNK, dl.TRACKED_CHUNK + 1, 23])
def test_tracked_samples_equals_the_continuation_over_the_whole_batch(needing):
    """`dl.tracked_samples` (the continuation on the samples that need it, a chunk at a time) gives every sample
    what the continuation vmapped over the whole batch with the others inactive gives: none, one, a full chunk,
    one more than a chunk, and all 23 samples needing it, scattered in the batch."""
    from jaxcal.closure.track import Tracked

    n = 23
    rng = np.random.default_rng(needing)
    q = jnp.asarray(rng.normal(size=(n, 3)))
    x0 = jnp.asarray(rng.normal(size=(n, 5)))
    need = jnp.asarray(np.isin(np.arange(n), rng.permutation(n)[:needing]))

    def run(qi, xi, active):  # a stand-in continuation: its result depends on the sample, inactive lanes keep x0
        steps = jnp.asarray(1 + jnp.sum(jnp.abs(qi)) * 10, jnp.int32)
        return Tracked(jnp.where(active, xi + jnp.sum(qi) * jnp.arange(5.0), xi), active & (qi[0] > 0),
                       jnp.where(active, steps, 0), active)

    got = jax.jit(lambda q, x, nd: dl.tracked_samples(run, q, x, nd))(q, x0, need)
    want = jax.vmap(run)(q, x0, need)
    np.testing.assert_allclose(got.theta, want.theta, rtol=1e-15, atol=1e-15)  # the same arithmetic, lanes of other widths
    for g, w in zip(got[1:], want[1:]):  # reached, steps, ref_ok: exactly
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_fit_jacobian_in_reverse_mode_matches_forward_mode_and_central_differences(rb):
    """The fits' Jacobian of the Delta (`core.data_residual_and_jacobian`: the closure presolved for the batch, then
    reverse mode sample by sample through `dl.forward_presolved`) against forward mode through `dl.forward` (its
    custom JVP) on every sample, and against central differences (h = 1e-6) of the residuals re-solving the closure
    on the samples that close. The geometry is perturbed (2 cm / 0.02 rad) so that a sample leaves the fast path for
    the continuation and some do not close (their penalty pose has no derivative in either mode)."""
    a0 = jc.perturb(rb, 2e-2, seed=2)  # 16 settings: 8 on the fast path, 1 tracked, 7 unclosed
    q = jnp.asarray(jc.random_configurations(rb, N, seed=2))
    qj = jax.jit(jax.vmap(lambda qi: dl.joint_variables(rb, a0, qi)))(q)  # compiled whole, not op by op
    fast_ok = jax.jit(jax.vmap(functools.partial(dl._fast_single, rb, a0)))(qj)[2]
    ok = np.asarray(dl.solve(rb, a0, q).ok)
    assert int(np.sum(ok & ~np.asarray(fast_ok))) >= 1 and not ok.all(), (fast_ok, ok)  # tracked and unclosed samples

    model = core.RobotDevice(rb, jc.measure.devices.as_device("position"))
    assert core.jacobian_mode(model) == "reverse"
    a_full = jnp.concatenate([a0, model.device.nominal])
    y = jnp.asarray(core.predicted(rb, model.device, a_full, q)) + 1e-4
    cov, w = jnp.zeros((N, 0)), jnp.ones((N, 3))
    r, J = jax.jit(lambda a: core.data_residual_and_jacobian(model, a, q, y, cov, w))(a_full)
    fn = lambda b, _: model.residuals(b, q, y, cov, w).reshape(-1)  # noqa: E731
    r_fwd, J_fwd = jax.jit(lambda a: core.residual_and_jacobian(fn, a, None))(a_full)
    np.testing.assert_allclose(r, r_fwd, rtol=0, atol=1e-15)
    assert rel_err(J, J_fwd) < 1e-12, rel_err(J, J_fwd)  # measured 4e-19

    # the fits' own Jacobian, from the tool's parameter twists (`dl.tool_and_twists`): the same first-order derivative
    r_tw, J_tw = jax.jit(lambda a: model.residual_and_jacobian(a, q, y, w))(a_full)
    np.testing.assert_allclose(r_tw, r, rtol=0, atol=1e-15)
    assert rel_err(J_tw, J) < 1e-12, rel_err(J_tw, J)  # measured 3.4e-15

    free = np.flatnonzero(rb.free_mask)
    rows = np.repeat(ok, 3)
    res = jax.jit(lambda x: model.residuals(a_full.at[free].set(x), q, y, cov, w).reshape(-1))
    fd = central_fd(lambda x: np.asarray(res(x))[rows], np.asarray(a_full[free]), h=1e-6)
    for got in (J, J_tw):
        err = rel_err(np.asarray(got)[rows][:, free], fd)
        assert err < 1e-6, err  # measured 5.6e-10
        assert np.all(np.asarray(got)[~rows][:, : rb.n_params] == 0.0)  # the device's columns move the penalty reading


def test_tool_twists_carry_gains_and_hold_the_robot(rb):
    """The tool's parameter twists (`dl.tool_and_twists`, the fits' Jacobian) where the actuator joints move with a
    parameter: j7.d1 (rod 1's length) made the gain of actuators 1 and 3 as well, so its twist sums the rod's and the
    gains' (seed 001 eq 4). The tool's derivative they give, d p = omega x p + v and d R = [omega]_x R, against forward
    mode through the implicit step of `dl.forward_presolved` at the same presolved closure; held, the twists are 0."""
    i = rb.index("j7.d1")
    geared = rb.replace(gains=(i, -1, i))
    a = jc.perturb(geared, 1e-3, seed=2)
    q = jnp.asarray(jc.random_configurations(geared, N, seed=2))
    pre = dl.presolve(geared, a, q)
    assert np.all(np.asarray(pre[1])), "every sample on the fast path"
    twists = jax.jit(jax.vmap(lambda qi, x, b, e, held: dl.tool_and_twists(geared, a, qi, (x, b, e), held),
                              (0, 0, 0, 0, None)))
    tool, Xi = twists(q, *pre, False)

    def pose_vector(a_, qi, pi):
        T = dl.forward_presolved(geared, a_, qi[None], jax.tree_util.tree_map(lambda v: v[None], pi))
        return jnp.concatenate([T.R[0].ravel(), T.p[0]])

    want = jax.jit(jax.vmap(lambda qi, x, b, e: jax.jacfwd(pose_vector)(a, qi, (x, b, e))))(q, *pre)  # (N, 12, P)
    omega, v = Xi[..., :3], Xi[..., 3:]
    dR = jnp.cross(omega[:, :, None, :], jnp.swapaxes(tool.R, -1, -2)[:, None], axis=-1)  # column by column
    got = jnp.concatenate([jnp.swapaxes(dR, -1, -2).reshape(N, -1, 9), jnp.cross(omega, tool.p[:, None]) + v], axis=-1)
    got = jnp.swapaxes(got, 1, 2)
    assert rel_err(got, want) < 1e-10, rel_err(got, want)  # measured 3.5e-13 (x_star to the Newton tolerance)
    assert rel_err(got[..., i], want[..., i]) < 1e-10 and float(jnp.abs(want[..., i]).max()) > 0.1  # 3.7e-13
    np.testing.assert_array_equal(twists(q, *pre, True)[1], 0.0)


def test_fast_path_closes_at_the_ball_joints_gimbal_lock_on_the_nominal_branch(rb):
    """A setting where rod 1's ball joint is at its gimbal lock (q8 ~ pi/2): the damped Newton closes it and the
    fast path keeps it, although q7 and q9 end > 0.5 rad from the start (the same nacelle, other angles: the branch
    test is on the nacelle frame). Its tool pose is the one the continuation from the nominal robot reaches."""
    a = jc.perturb(rb, 1e-3, seed=1)
    q = jnp.asarray(jc.random_configurations(rb, 125, seed=2))[35:36]
    qj = jax.jit(jax.vmap(lambda qi: dl.joint_variables(rb, a, qi)))(q)  # compiled whole, not op by op
    x0, x_fast, fast_ok = jax.jit(jax.vmap(functools.partial(dl._fast_single, rb, a)))(qj)[:3]
    assert abs(float(x0[0, 3]) - np.pi / 2) < 0.05 and float(jnp.max(jnp.abs(x_fast - x0))) > 0.5  # gimbal lock
    assert bool(fast_ok[0])
    tracked = jax.jit(lambda qi, xi: dl._track(rb, a, qi, xi))(qj[0], x0[0])
    assert bool(tracked.reached)

    @jax.jit  # compiled whole, not op by op
    def nacelles_and_tool(qi, x_a, x_b):
        st = dl._statics(rb, a)
        fixed = dl._fixed(rb, st, qi)
        ref = dl._nacelle(rb, st, fixed, x_b)
        return dl._nacelle(rb, st, fixed, x_a), ref, ref.compose(dl._local(st, dl.TOOL)).p

    fast, ref, tool = nacelles_and_tool(qj[0], x_fast[0], tracked.theta)
    assert float(jnp.max(jnp.abs(fast.p - ref.p))) < 1e-10 and float(jnp.max(jnp.abs(fast.R - ref.R))) < 1e-9
    np.testing.assert_allclose(jc.forward(rb, a, q).p, tool[None], atol=1e-10)
