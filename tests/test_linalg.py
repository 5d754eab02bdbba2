"""`jaxcal.linalg.solve_small`: the LAPACK-free dense solve of the closures (see its module docstring for
why: a batched LU inside a vmapped Jacobian deadlocked XLA's CPU thread pool)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.linalg import solve_small, solve_spd

# Compiled whole: called op by op, the unrolled elimination compiled ~100 small programs per size (~2 s of a test run).
solve = jax.jit(solve_small)


@pytest.mark.parametrize("n", [1, 2, 5, 9])
def test_matches_numpy_vector_and_matrix_rhs(rng, n):
    A = rng.normal(size=(n, n)) + n * np.eye(n)
    A[[0, -1]] = A[[-1, 0]]  # a zero-free but permuted diagonal: pivoting has to swap rows
    b, B = rng.normal(size=n), rng.normal(size=(n, 3))
    assert rel_err(solve(jnp.asarray(A), jnp.asarray(b)), np.linalg.solve(A, b)) < 1e-13
    assert rel_err(solve(jnp.asarray(A), jnp.asarray(B)), np.linalg.solve(A, B)) < 1e-13


def test_needs_pivoting():
    """A zero leading entry: elimination without row swaps divides by zero."""
    A = np.array([[0.0, 2.0, 1.0], [1.0, 1.0, 0.0], [3.0, 0.0, 1.0]])
    b = np.array([1.0, 2.0, 3.0])
    assert rel_err(solve(jnp.asarray(A), jnp.asarray(b)), np.linalg.solve(A, b)) < 1e-14


def test_vmap_and_singular(rng):
    A = rng.normal(size=(50, 5, 5)) + 5 * np.eye(5)
    b = rng.normal(size=(50, 5))
    x = jax.jit(jax.vmap(solve_small))(A, b)
    assert rel_err(x, np.linalg.solve(A, b[..., None])[..., 0]) < 1e-13
    assert not np.all(np.isfinite(solve(jnp.zeros((3, 3)), jnp.ones(3))))
    with pytest.raises(ValueError, match="square"):
        solve(jnp.zeros((3, 2)), jnp.ones(3))


@pytest.mark.parametrize("n", [1, 2, 5, 9])
def test_spd_solve_matches_numpy_and_refuses_what_is_not_positive_definite(rng, n):
    """`solve_spd` on J^T J + mu I (the closures' normal equations), conditioned up to ~1e8: relative error
    against numpy < 1e-8 (backward stable: forward error ~ cond x 1e-16); singular or indefinite: non-finite."""
    solve_pd = jax.jit(solve_spd)
    J = rng.normal(size=(n + 2, n)) * np.logspace(0, -4, n)  # columns scaled apart: cond(J^T J) ~ 1e8
    for A in (J.T @ J, J.T @ J + 1e-3 * np.eye(n)):
        b = rng.normal(size=n)
        assert rel_err(solve_pd(jnp.asarray(A), jnp.asarray(b)), np.linalg.solve(A, b)) < 1e-8
    assert not np.all(np.isfinite(solve_pd(jnp.zeros((n, n)), jnp.ones(n))))
    indefinite = np.diag(np.r_[-1.0, np.ones(n - 1)])
    assert not np.all(np.isfinite(solve_pd(jnp.asarray(indefinite), jnp.ones(n))))
    with pytest.raises(ValueError, match="square"):
        solve_pd(jnp.zeros((n, n + 1)), jnp.ones(n))


def test_gradient_matches_central_differences(rng):
    """d x / d(A, b) by jacfwd against central differences (float64); relative error < 1e-8."""
    n = 5
    A0 = rng.normal(size=(n, n)) + n * np.eye(n)
    b0 = rng.normal(size=n)

    @jax.jit
    def f(v):
        return solve_small(jnp.asarray(v[:n * n]).reshape(n, n), jnp.asarray(v[n * n:]))

    v0 = np.concatenate([A0.ravel(), b0])
    J = jax.jacfwd(f)(jnp.asarray(v0))
    assert rel_err(J, central_fd(lambda v: np.asarray(f(v)), v0)) < 1e-8


def test_delta_jacobian_has_no_lapack_call():
    """The vmapped Jacobian of the Delta's closed forward (what `jc.gap.diagnose` compiles) calls no LAPACK
    kernel: the regression guard for the thread-pool deadlock (the compiled module is inspected, nothing run)."""
    robot = jc.robots.get("delta")
    q = jnp.asarray(np.tile(robot.home_np, (8, 1)))

    def rows(a):
        return jc.forward(robot, a, q).p.reshape(-1)

    hlo = jax.jit(jax.jacfwd(rows)).lower(jnp.asarray(robot.nominal)).as_text()
    assert "getrf" not in hlo and "lapack" not in hlo.lower()
    hlo_solve = jax.jit(jax.vmap(jnp.linalg.solve)).lower(jnp.ones((8, 5, 5)), jnp.ones((8, 5))).as_text()
    assert "getrf" in hlo_solve  # the check would see an LU if one were there

