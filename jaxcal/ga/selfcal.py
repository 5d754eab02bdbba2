"""Self-calibration from joint readings only (seed 000 §7.4): pointing tool with two targets at a
known distance (eq 7.9-7.12), and the pose-target variant.

The pointer (e.g. a laser along the tool z axis) is aimed at target i from configurations q_ik;
the pointer is a virtual prismatic joint of unknown extension lambda_ik whose tip is the target
(eq 7.10): o(q_ik) + lambda_ik u(q_ik) = p_i. Only joint readings are recorded; the targets'
positions are unknown but their distance d is known (eq 7.9, 7.11). Eq 7.12 is solved here with
the nuisance unknowns eliminated in closed form: for parameters a, p_i is the point nearest (least
squares) to the lines of its aims, and the residual stacks each line's distance to p_i
((I - u u^T)(p_i - o)) and w_d (|p_1 - p_2| - d). The same residual drives LM and the GA.

Pose-target variant (the end of §7.4): M full-pose targets (e.g. three-point targets) on a fixture
whose poses X_i relative to each other were established in advance; the fixture's pose W is
unknown. The end-effector is matched to target i at joint readings q_i: F(q_i, a) = W X_i. W is
eliminated by taking every target relative to the first: F(q_0)^-1 F(q_i) = X_0^-1 X_i, and the
residual stacks, for i = 1..M-1, the position difference (m) and the rotation vector of the
rotation difference (rad) of the two sides (the nonlinear formulation of eq 7.12 for full poses).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal.fit.base import base_set
from jaxcal.forward import forward
from jaxcal.kin.rotations import log_so3


def _lines(robot, a, q):
    tip = forward(robot, a, q)
    return tip.p, tip.R[..., :, 2]


def nearest_point(o, u):
    """Least-squares intersection of lines o_k + t u_k: solve sum(I - u u^T) p = sum(I - u u^T) o."""
    P = jnp.eye(3) - u[:, :, None] * u[:, None, :]
    return jnp.linalg.solve(P.sum(0), jnp.einsum("kij,kj->i", P, o))


def residual(robot, a, q1, q2, d, w_d=1.0):
    """Stacked self-calibration residual (eq 7.12) for aims q1 at target 1 and q2 at target 2."""
    o1, u1 = _lines(robot, a, q1)
    o2, u2 = _lines(robot, a, q2)
    p1, p2 = nearest_point(o1, u1), nearest_point(o2, u2)

    def off_line(p, o, u):
        v = p - o
        return v - jnp.sum(v * u, -1, keepdims=True) * u

    dist = jnp.linalg.norm(p1 - p2) - d
    return jnp.concatenate([off_line(p1, o1, u1).reshape(-1), off_line(p2, o2, u2).reshape(-1), w_d * dist[None]])


def pose_target_residual(robot, a, q, X):
    """Pose-target residual: q (M, n) joint readings matching targets with fixture poses X (M, 4, 4);
    6 (M - 1) entries: F(q_0)^-1 F(q_i) against X_0^-1 X_i (position, then rotation vector)."""
    tip = forward(robot, a, q)
    X = jnp.asarray(X)
    R0, p0 = tip.R[0], tip.p[0]
    XR0, Xp0 = X[0, :3, :3], X[0, :3, 3]
    rel_p = (tip.p[1:] - p0) @ R0                       # R_0^T (p_i - p_0), rows
    rel_R = jnp.einsum("ji,njk->nik", R0, tip.R[1:])     # R_0^T R_i
    want_p = (X[1:, :3, 3] - Xp0) @ XR0
    want_R = jnp.einsum("ji,njk->nik", XR0, X[1:, :3, :3])
    rot = jax.vmap(log_so3)(jnp.einsum("nji,njk->nik", want_R, rel_R))
    return jnp.concatenate([rel_p - want_p, rot], axis=1).reshape(-1)


def _identifiable_from(res, a, free_idx, priority):
    J = np.asarray(jax.jacfwd(res)(jnp.asarray(a)))[:, free_idx]
    return base_set(J, np.asarray(priority)[free_idx]), int(np.linalg.matrix_rank(J))


def identifiable(robot, a, q1, q2, d, free_idx):
    """Base set (seed 001 App. III) of the free parameters for the two-target method, and the Jacobian rank."""
    return _identifiable_from(lambda x: residual(robot, x, q1, q2, d), a, free_idx, robot.priority)


def pose_target_identifiable(robot, a, q, X, free_idx):
    """Base set of the free parameters for the pose-target method, and the Jacobian rank."""
    return _identifiable_from(lambda x: pose_target_residual(robot, x, q, X), a, free_idx, robot.priority)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _lm(residual_fn, robot, x0, a_ref, mask, args):
    def fn(x, _):
        a = jnp.where(mask > 0, x, a_ref)
        return jnp.concatenate([residual_fn(robot, a, *args), (1.0 - mask) * (x - a_ref)])

    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-15), x0, None, max_steps=200, throw=False)
    return jnp.where(mask > 0, sol.value, a_ref), sol.result == optx.RESULTS.successful


def _identify_lm(residual_fn, robot, args, est_idx, a0):
    a0 = robot.nominal if a0 is None else jnp.asarray(a0)
    mask = jnp.zeros(robot.n_params).at[jnp.asarray(est_idx)].set(1.0)
    a, ok = _lm(residual_fn, robot, a0, a0, mask, args)
    return a, bool(ok)


def identify_lm(robot, q1, q2, d, est_idx, a0=None):
    """LM on the base-set parameters est_idx (others pinned at a0), two-target method."""
    return _identify_lm(residual, robot, (jnp.asarray(q1), jnp.asarray(q2), jnp.float64(d)), est_idx, a0)


def identify_pose_target_lm(robot, q, X, est_idx, a0=None):
    """LM on the base-set parameters est_idx (others pinned at a0), pose-target method."""
    return _identify_lm(pose_target_residual, robot, (jnp.asarray(q), jnp.asarray(X)), est_idx, a0)


def aim_configurations(robot, a, target, q_starts):
    """Joint values aiming the pointer at `target` (IK by LM from each start, vmapped); returns
    (q (K, n), off-line distance (K,)) so the caller can keep the converged ones."""
    def fn(q, _):
        o, u = _lines(robot, a, q)
        v = target - o
        return v - jnp.dot(v, u) * u

    def one(q0):
        sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-13, atol=1e-15), q0, None, max_steps=200, throw=False)
        return sol.value, jnp.linalg.norm(fn(sol.value, None))

    return jax.jit(jax.vmap(one))(jnp.asarray(q_starts))


def _identify_ga(residual_fn, robot, args, est_idx, population, generations, bound, seed, a0, options):
    """The GA (jaxcal.ga.core) on residual_fn: cost = sum of squares, variables dg on est_idx."""
    from jaxcal.ga import core

    a0 = robot.nominal if a0 is None else jnp.asarray(a0)
    idx = jnp.asarray(est_idx)
    opts = core.GAOptions(population=population, generations=generations, **options)

    def fitness_of(dg, data):
        return jnp.sum(residual_fn(robot, data["a0"].at[idx].add(dg), *data["args"]) ** 2)

    payload = dict(a0=a0, args=args)
    lb, ub = -bound * jnp.ones(len(est_idx)), bound * jnp.ones(len(est_idx))
    _, init_random = core.make_init_fn(fitness_of, opts)
    state = init_random(jax.random.split(jax.random.PRNGKey(seed), 1), payload, lb, ub)
    state, best, _ = core.make_chunk_fn(fitness_of, opts, generations)(state, payload, lb, ub)
    dg, _ = jax.vmap(core.best_individual)(state)
    return a0.at[idx].add(dg[0]), np.asarray(best[0])


def identify_ga(robot, q1, q2, d, est_idx, *, population=50, generations=250, bound=0.005, seed=0, a0=None, **options):
    """The GA on the two-target residual. Returns (a, best cost per generation)."""
    args = (jnp.asarray(q1), jnp.asarray(q2), jnp.float64(d))
    return _identify_ga(residual, robot, args, est_idx, population, generations, bound, seed, a0, options)


def identify_pose_target_ga(robot, q, X, est_idx, *, population=50, generations=250, bound=0.005, seed=0, a0=None,
                            **options):
    """The GA on the pose-target residual. Returns (a, best cost per generation)."""
    args = (jnp.asarray(q), jnp.asarray(X))
    return _identify_ga(pose_target_residual, robot, args, est_idx, population, generations, bound, seed, a0, options)


def pose_configurations(robot, a, X, q_starts):
    """Joint values matching the tool frame to the poses X (M, 4, 4) (IK by LM from q_starts (M, n),
    vmapped); returns (q (M, n), pose residual norm (M,))."""
    def fn(q, target):
        tip = forward(robot, a, q)
        return jnp.concatenate([tip.p - target[:3, 3], log_so3(target[:3, :3].T @ tip.R)])

    def one(q0, target):
        sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-13, atol=1e-15), q0, target, max_steps=200,
                                 throw=False)
        return sol.value, jnp.linalg.norm(fn(sol.value, target))

    return jax.jit(jax.vmap(one))(jnp.asarray(q_starts), jnp.asarray(X))
