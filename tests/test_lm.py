"""jaxcal's Levenberg-Marquardt (jaxcal.fit.lm), the core's default solver."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxcal.fit import lm


def rosenbrock(z, args):
    """Rosenbrock's valley as least squares: minimum 0 at (1, 1), reached only along the curved valley."""
    return jnp.stack([args * (z[1] - z[0] ** 2), 1.0 - z[0]])


def exponentials(z, t):
    """Sum of two decaying exponentials, zero residual at z = (1, 0.5, 2, 3) for the data made below."""
    return z[0] * jnp.exp(-z[2] * t) + z[1] * jnp.exp(-z[3] * t) - (jnp.exp(-2 * t) + 0.5 * jnp.exp(-3 * t))


def test_reaches_the_minimum_of_rosenbrock_and_of_an_exponential_fit():
    res = jax.jit(lambda z0: lm.least_squares(rosenbrock, z0, 10.0, max_steps=200, rtol=1e-10, atol=1e-12))(
        jnp.array([-1.2, 1.0]))
    assert bool(res.converged) and int(res.steps) < 100
    np.testing.assert_allclose(np.asarray(res.z), [1.0, 1.0], atol=1e-9)
    t = jnp.linspace(0.0, 2.0, 40)
    res = lm.least_squares(exponentials, jnp.array([0.8, 0.7, 1.5, 3.5]), t, max_steps=200, rtol=1e-10, atol=1e-12)
    assert bool(res.converged) and float(res.cost) < 1e-20
    np.testing.assert_allclose(np.asarray(res.z), [1.0, 0.5, 2.0, 3.0], atol=1e-7)


def test_agrees_with_optimistix_on_a_noisy_fit():
    """Noisy data (nonzero residual at the optimum): both solvers stop at the same least-squares estimate."""
    t = jnp.linspace(0.0, 2.0, 40)
    noise = 1e-3 * jnp.asarray(np.random.default_rng(0).standard_normal(40))
    fn = lambda z, t: exponentials(z, t) + noise  # noqa: E731
    z0 = jnp.array([0.8, 0.7, 1.5, 3.5])
    ours = lm.least_squares(fn, z0, t, max_steps=200, rtol=1e-10, atol=1e-12)
    theirs = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12), z0, t, max_steps=200, throw=False)
    assert bool(ours.converged) and theirs.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(ours.z), np.asarray(theirs.value), atol=1e-7)
    assert abs(float(ours.cost) - float(jnp.sum(fn(theirs.value, t) ** 2))) < 1e-12


def test_unconverged_after_max_steps_and_converged_at_an_exact_start():
    short = lm.least_squares(rosenbrock, jnp.array([-1.2, 1.0]), 10.0, max_steps=3, rtol=1e-10, atol=1e-12)
    assert not bool(short.converged) and int(short.steps) == 3
    exact = lm.least_squares(rosenbrock, jnp.array([1.0, 1.0]), 10.0, max_steps=50, rtol=1e-10, atol=1e-12)
    assert bool(exact.converged) and int(exact.steps) == 1 and np.asarray(exact.z).tolist() == [1.0, 1.0]


def test_residual_and_jacobian_is_jacfwd():
    z = jnp.array([0.3, -0.7, 1.1, 2.5])
    t = jnp.linspace(0.0, 2.0, 7)
    r, J = lm.residual_and_jacobian(exponentials, z, t)
    np.testing.assert_array_equal(np.asarray(r), np.asarray(exponentials(z, t)))
    np.testing.assert_allclose(np.asarray(J), np.asarray(jax.jacfwd(exponentials)(z, t)), rtol=1e-14, atol=1e-15)


def test_vmapped_batch_equals_single_solves():
    starts = jnp.array([[-1.2, 1.0], [0.5, 0.5], [2.0, 3.0]])
    batch = jax.vmap(lambda z0: lm.least_squares(rosenbrock, z0, 10.0, max_steps=200, rtol=1e-10, atol=1e-12))(starts)
    for i, z0 in enumerate(starts):
        one = lm.least_squares(rosenbrock, z0, 10.0, max_steps=200, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(batch.z[i]), np.asarray(one.z), atol=1e-12)
        assert int(batch.steps[i]) == int(one.steps)


def test_history_is_the_cost_after_each_step():
    """The history recorded in the loop is what stepping `lm.step` by hand gives, then NaN. The step is compiled as
    the loop is: stepped eagerly, rounding at a cost of ~1e-27 decided the stopping test one step apart."""
    z0, steps = jnp.array([-1.2, 1.0]), 60
    hist = np.asarray(lm.least_squares(rosenbrock, z0, 10.0, max_steps=steps, rtol=1e-10, atol=1e-12).history)
    one_step = jax.jit(lambda s: lm.step(rosenbrock, s, 10.0, 1e-10, 1e-12))
    s = lm.init(rosenbrock, z0, 10.0)
    by_hand = [float(s.r @ s.r)]
    while not bool(s.converged) and int(s.steps) < steps:
        s = one_step(s)
        by_hand.append(float(s.r @ s.r))
    n = len(by_hand)
    assert hist.shape == (steps + 1,) and n < steps
    np.testing.assert_allclose(hist[:n], by_hand, rtol=1e-8, atol=1e-14)  # eager vs compiled rounding
    assert np.all(np.isnan(hist[n:])) and hist[n - 1] < 1e-20


def test_a_step_at_round_off_ends_the_run(monkeypatch):
    """A step below the tolerances whose cost change is round-off (here +2e-12 of the cost) is accepted and ends the
    run (`lm.ROUND_OFF`); judged by its gain ratio alone (a ratio of round-off errors at an optimum) it was rejected,
    and the run went on while lam grew. r(z) = 1 + z^2 with the Jacobian given as 1e6 (a step of -1e-6)."""
    fn = lambda z, args: 1.0 + z**2  # noqa: E731
    jac = lambda z, args: (fn(z, args), jnp.full((1, 1), 1e6))  # noqa: E731
    s0 = lm.init(fn, jnp.zeros(1), None, jac)
    s1 = lm.step(fn, s0, None, 0.0, 1e-5, jac)
    assert bool(s1.converged) and float(s1.z[0]) == pytest.approx(-1e-6, rel=1e-9)
    res = lm.least_squares(fn, jnp.zeros(1), None, max_steps=50, rtol=0.0, atol=1e-5, jac=jac)
    assert bool(res.converged) and int(res.steps) == 1
    monkeypatch.setattr(lm, "ROUND_OFF", -np.inf)  # the gain-ratio test alone
    s1 = lm.step(fn, s0, None, 0.0, 1e-5, jac)
    assert not bool(s1.converged) and float(s1.z[0]) == 0.0


def test_secant_acceleration_is_the_second_order_correction():
    """a = -(J^T J + lam I)^-1 J^T r_vv with r_vv the exact second directional derivative (nested jvp) of a residual
    quadratic in z, where the last step's bend r(z) - r(z_prev) - J(z_prev) last is exactly r_ll / 2: for v along
    the last step the correction matches to < 1e-7 relative; for v across it (cosine below ACCEL_COS) it is 0."""
    A = jnp.asarray(np.random.default_rng(1).standard_normal((6, 3)))
    B = 0.1 * jnp.asarray(np.random.default_rng(2).standard_normal((6, 3, 3)))
    fn = lambda z, args: A @ z + 0.5 * jnp.einsum("kij,i,j->k", B, z, z) - 1.0  # noqa: E731
    z = jnp.array([0.3, -0.2, 0.5])
    r, J = lm.residual_and_jacobian(fn, z, None)
    lam = 0.1
    U, v = lm.damped_factor(J, r, lam)
    np.testing.assert_allclose(np.asarray(U.T @ U), np.asarray(J.T @ J + lam * jnp.eye(3)), rtol=1e-12, atol=1e-12)
    rvv = jax.jvp(lambda u: jax.jvp(lambda w: fn(w, None), (u,), (v,))[1], (z,), (v,))[1]
    expected = -jnp.linalg.solve(J.T @ J + lam * jnp.eye(3), J.T @ rvv)
    assert 2 * float(jnp.linalg.norm(expected)) <= lm.ACCEL_MAX * float(jnp.linalg.norm(v))  # a usable correction
    for last in (0.5 * v, -2.0 * v):  # the last step along v, shorter or longer, either sign
        z_prev = z - last
        r_prev, J_prev = lm.residual_and_jacobian(fn, z_prev, None)
        a = lm.secant_acceleration(J, U, v, last, r - r_prev - J_prev @ last)
        assert float(jnp.linalg.norm(a - expected) / jnp.linalg.norm(expected)) < 1e-7
        too_bent = 100.0 * (r - r_prev - J_prev @ last)  # a correction of more than ACCEL_MAX / 2 of the step is not used
        assert float(jnp.linalg.norm(lm.secant_acceleration(J, U, v, last, too_bent))) == 0.0
    across = jnp.cross(v, jnp.array([1.0, 0.0, 0.0]))
    r_prev, J_prev = lm.residual_and_jacobian(fn, z - across, None)
    assert float(jnp.linalg.norm(lm.secant_acceleration(J, U, v, across, r - r_prev - J_prev @ across))) == 0.0
    assert float(jnp.linalg.norm(lm.secant_acceleration(J, U, v, jnp.zeros(3), jnp.zeros(6)))) == 0.0  # no step yet


def test_geodesic_acceleration_follows_the_curved_valley(monkeypatch):
    """Rosenbrock's valley with a wall of 100 (narrow and curved): the accelerated steps reach (1, 1) in fewer
    iterations than the plain damped steps (acceleration switched off by ACCEL_MAX = 0), to the same point: 23 against
    42 here (with the wall of 10: 22 against 23; 1000: 54 against 198)."""
    solve = lambda: lm.least_squares(rosenbrock, jnp.array([-1.2, 1.0]), 100.0, max_steps=500, rtol=1e-10, atol=1e-12)  # noqa: E731
    accelerated = solve()
    monkeypatch.setattr(lm, "ACCEL_MAX", 0.0)
    plain = solve()
    assert bool(accelerated.converged) and bool(plain.converged)
    np.testing.assert_allclose(np.asarray(accelerated.z), [1.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(np.asarray(plain.z), [1.0, 1.0], atol=1e-9)
    assert int(accelerated.steps) < int(plain.steps), (int(accelerated.steps), int(plain.steps))


def test_a_step_on_the_free_columns_alone_is_the_masked_step():
    """`lm.step_columns` (width): the damped step solved on the free unknowns' columns gathered (with one zero padding
    column) is the step solved on every column with the others zeroed: Rosenbrock's valley (wall 100) embedded in five
    unknowns of which two move and three are held, in scattered places, the held ones entering the residual too. The
    same iterations (accelerated ones among them; the last, at round-off, may differ by one), the same estimate to
    1e-12, held entries untouched, J with every column."""
    def embedded(z, args):
        return jnp.concatenate([rosenbrock(z[jnp.array([3, 1])], args), 0.1 * (z[jnp.array([0, 2, 4])] - 0.5) * z[1]])

    z0 = jnp.array([0.2, 1.0, -0.3, -1.2, 0.7])
    free = jnp.array([0.0, 1.0, 0.0, 1.0, 0.0])
    masked = jax.jit(lambda z: lm.least_squares(embedded, z, 100.0, max_steps=500, rtol=1e-10, atol=1e-12, free=free))(z0)
    idx, valid = lm.step_columns(free, 3)
    assert np.asarray(idx)[:2].tolist() == [1, 3] and np.asarray(valid).tolist() == [True, True, False]
    for width in (2, 3):
        gathered = jax.jit(lambda z: lm.least_squares(embedded, z, 100.0, max_steps=500, rtol=1e-10, atol=1e-12,
                                                      free=free, width=width))(z0)  # noqa: B023
        assert bool(gathered.converged) and abs(int(gathered.steps) - int(masked.steps)) <= 1  # the last: round-off
        assert int(masked.steps) > lm.ACCEL_AFTER  # accelerated steps taken
        np.testing.assert_allclose(np.asarray(gathered.z), np.asarray(masked.z), rtol=0, atol=1e-12)
        assert np.asarray(gathered.z)[[0, 2, 4]].tolist() == np.asarray(z0)[[0, 2, 4]].tolist()
        np.testing.assert_allclose(np.asarray(gathered.J), np.asarray(jax.jacfwd(embedded)(gathered.z, 100.0)), rtol=1e-14,
                                   atol=1e-14)


def test_rows_of_one_entry_folded_into_the_damping_give_the_damped_step():
    """`lm.damped_factor(..., data_rows)`: rows past data_rows with one non-zero entry each (the core's bias, pin and
    bound rows) folded into the damping rows give the same step and U^T U = J^T J + lam I as the whole stack: 30 data
    rows, 6 columns, singleton rows on columns 0, 2 (twice) and 5, an all-zero row, lam 0 and 1e-3, to 1e-12. Folding
    wrongly (the rows dropped) misses by the bias rows' pull."""
    rng = np.random.default_rng(3)
    data, n = rng.standard_normal((30, 6)), 6
    singles = np.zeros((5, n))
    singles[0, 0], singles[1, 2], singles[2, 2], singles[4, 5] = 0.7, -1.3, 2.0, 1e3  # row 3: all zero
    J = jnp.asarray(np.concatenate([data, singles]))
    r = jnp.asarray(rng.standard_normal(35))
    for lam in (0.0, 1e-3):
        U, step = lm.damped_factor(J, r, lam)
        U_f, step_f = lm.damped_factor(J, r, lam, data_rows=30)
        np.testing.assert_allclose(np.asarray(step_f), np.asarray(step), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(U_f.T @ U_f), np.asarray(J.T @ J + lam * jnp.eye(n)), rtol=1e-12, atol=1e-9)
        dropped = lm.damped_factor(J[:30], r[:30], lam)[1]
        assert float(jnp.max(jnp.abs(dropped - step))) > 1e-3


def test_a_last_step_of_no_predicted_gain_within_the_tolerances_is_not_evaluated():
    """Right after an accepted step, a step whose predicted decrease is at round-off and which is within the step
    tolerances ends the run unevaluated: z is returned as it is, with the residual and Jacobian evaluated there, and
    the run evaluates r and J twice (the start, the first step) where evaluating that last step made it three times.
    r(z) = (z0 - 1, z1 - 2, 1): the first step (damping 1e-9) lands 1e-9 short of (1, 2), the second would move
    1e-9 (tolerance 1e-8 + 1e-6 |z|) for a predicted decrease of ~1e-18 of the cost."""
    calls = []
    J = jnp.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])

    def jac(z, args):
        jax.debug.callback(lambda: calls.append(1))
        return jnp.stack([z[0] - 1.0, z[1] - 2.0, jnp.ones((), z.dtype)]), J

    res = lm.least_squares(lambda z, args: jac(z, args)[0], jnp.zeros(2), None, max_steps=50, rtol=1e-6, atol=1e-8, jac=jac)
    jax.block_until_ready(res)
    assert bool(res.converged) and int(res.steps) == 2 and len(calls) == 2
    np.testing.assert_allclose(np.asarray(res.z), [1.0, 2.0], rtol=0, atol=1e-8)
    np.testing.assert_array_equal(np.asarray(res.r), [res.z[0] - 1.0, res.z[1] - 2.0, 1.0])
    assert float(res.history[2]) == float(res.history[1])  # the last step left the cost as it was: not taken


def test_a_step_of_negligible_predicted_gain_ends_the_run(monkeypatch):
    """A step whose predicted decrease is at round-off (here 1e-18 of the cost, which rounds to 0) ends the run
    though it is far above the tolerances, kept since the cost did not rise: z is optimal to working precision.
    Judged by the tolerances alone the run went on (here two more steps; on an ill-conditioned fit, whose round-off
    steps exceed the residual tolerance, rejections while lam grew: tests/test_core.py's far-frame Stanford arm).
    r(z) = (1, 1e-6 z) from z = 1e-3: the step is -1e-3, to the optimum z = 0 up to the QR's round-off,
    eps |r| / |J| ~ 1e-10 (measured -8.2e-11)."""
    fn = lambda z, args: jnp.concatenate([jnp.ones(1), 1e-6 * z])  # noqa: E731
    res = lm.least_squares(fn, jnp.full(1, 1e-3), None, max_steps=50, rtol=1e-10, atol=1e-12)
    assert bool(res.converged) and int(res.steps) == 1 and abs(float(res.z[0])) < 1e-9
    monkeypatch.setattr(lm, "ROUND_OFF", -np.inf)  # the tolerances alone
    s1 = lm.step(fn, lm.init(fn, jnp.full(1, 1e-3), None), None, 1e-10, 1e-12)
    assert not bool(s1.converged) and abs(float(s1.z[0])) < 1e-9
    res = lm.least_squares(fn, jnp.full(1, 1e-3), None, max_steps=50, rtol=1e-10, atol=1e-12)
    assert int(res.steps) > 1  # 3 measured: its round-off steps (~1e-10) exceed atol until one happens not to


def test_a_start_stops_at_a_small_predicted_gain_without_evaluating_that_step():
    """`stop` (the core's frames-only start, `core.START_STOP`): the run ends, converged, at a step predicted to lower
    the cost by at most stop times it, that step not evaluated. Noisy two-exponential fit from (0.8, 0.7, 1.5, 3.5):
    8 evaluations of r and J without, 6 with stop = 1e-6, the cost then within 1e-6 of the optimum's (measured 2e-7)."""

    def counted(calls):
        def jac(z, t):
            jax.debug.callback(lambda: calls.append(1))
            return lm.residual_and_jacobian(noisy_exponentials, z, t)
        return jac

    t = jnp.linspace(0.0, 2.0, 40)
    runs = {}
    for stop in (0.0, 1e-6):
        calls = []
        res = lm.least_squares(noisy_exponentials, jnp.array([0.8, 0.7, 1.5, 3.5]), t, max_steps=200, rtol=1e-10,
                               atol=1e-12, jac=counted(calls), stop=stop)
        jax.block_until_ready(res)
        runs[stop] = (res, len(calls))
    (full, n_full), (start, n_start) = runs[0.0], runs[1e-6]
    assert bool(full.converged) and bool(start.converged)
    assert n_start < n_full, (n_start, n_full)
    assert float(full.cost) <= float(start.cost) <= float(full.cost) * (1 + 1e-6)
    assert float(start.history[int(start.steps)]) == float(start.history[int(start.steps) - 1])  # the last step not taken


def test_a_start_does_not_stop_on_a_step_that_raised_damping_held_back():
    """After rejections the damping is large and the damped step predicts a tiny decrease however far the optimum
    is: `stop` then does not end the run (only while lam is at most its start value `initial_damping`)."""
    t = jnp.linspace(0.0, 2.0, 40)
    rj = lambda z, args: lm.residual_and_jacobian(noisy_exponentials, z, args)  # noqa: E731
    s = lm.init(noisy_exponentials, jnp.array([0.8, 0.7, 1.5, 3.5]), t)
    s = s._replace(lam=s.lam * 1e16)  # as after ~10 rejections in a row (each multiplies lam by nu, which doubles)
    v = lm.damped_step(s.J, s.r, s.lam)
    cost = float(s.r @ s.r)
    assert 0.0 < cost - float(jnp.sum((s.r + s.J @ v) ** 2)) <= 1e-6 * cost  # the stop's test alone would end here
    after = lm.advance(rj, s, t, 1e-10, 1e-12, jnp.asarray(False), stop=1e-6)
    assert not bool(after.converged) and float(jnp.max(jnp.abs(after.z - s.z))) > 0.0  # evaluated and taken
    at_start = lm.advance(rj, s._replace(lam=lm.initial_damping(s.J) * 1e-6), t, 1e-10, 1e-12, jnp.asarray(False), stop=1e-6)
    assert not bool(at_start.converged)  # far from the optimum an undamped step predicts a large decrease: no stop


def noisy_exponentials(z, t):
    """`exponentials` plus fixed noise of 1e-3 (40 points): a residual of ~5e-3 at the optimum."""
    return exponentials(z, t) + 1e-3 * jnp.asarray(np.random.default_rng(0).standard_normal(t.shape[0]))
