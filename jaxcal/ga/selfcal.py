"""Self-calibration with a pointing tool and two targets at a known distance (seed 000 §7.4).

The pointer (e.g. a laser along the tool z axis) is aimed at target i from configurations q_ik;
the pointer is a virtual prismatic joint of unknown extension lambda_ik whose tip is the target
(eq 7.10): o(q_ik) + lambda_ik u(q_ik) = p_i. Only joint readings are recorded; the targets'
positions are unknown but their distance d is known (eq 7.9, 7.11). Eq 7.12 is solved here with
the nuisance unknowns eliminated in closed form: for parameters a, p_i is the point nearest (least
squares) to the lines of its aims, and the residual stacks each line's distance to p_i
((I - u u^T)(p_i - o)) and w_d (|p_1 - p_2| - d). The same residual drives LM and the GA.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal.fit.base import base_set
from jaxcal.forward import forward


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


def identifiable(robot, a, q1, q2, d, free_idx):
    """Base set (seed 001 App. III) of the free parameters for this method, and the Jacobian rank."""
    J = np.asarray(jax.jacfwd(lambda x: residual(robot, x, q1, q2, d))(jnp.asarray(a)))[:, free_idx]
    bs = base_set(J, np.asarray(robot.priority)[free_idx])
    return bs, int(np.linalg.matrix_rank(J))


@functools.partial(jax.jit, static_argnums=0)
def _lm(robot, x0, a_ref, mask, q1, q2, d):
    def fn(x, _):
        a = jnp.where(mask > 0, x, a_ref)
        return jnp.concatenate([residual(robot, a, q1, q2, d), (1.0 - mask) * (x - a_ref)])

    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-15), x0, None, max_steps=200, throw=False)
    return jnp.where(mask > 0, sol.value, a_ref), sol.result == optx.RESULTS.successful


def identify_lm(robot, q1, q2, d, est_idx, a0=None):
    """LM on the base-set parameters est_idx (others pinned at a0)."""
    a0 = robot.nominal if a0 is None else jnp.asarray(a0)
    mask = jnp.zeros(robot.n_params).at[jnp.asarray(est_idx)].set(1.0)
    a, ok = _lm(robot, a0, a0, mask, jnp.asarray(q1), jnp.asarray(q2), jnp.float64(d))
    return a, bool(ok)


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


def identify_ga(robot, q1, q2, d, est_idx, *, population=50, generations=250, bound=0.005, seed=0, a0=None, **options):
    """The GA (jaxcal.ga.core) on the same residual: cost = sum of squares, variables dg on est_idx.
    Returns (a, best cost per generation)."""
    from jaxcal.ga import core

    a0 = robot.nominal if a0 is None else jnp.asarray(a0)
    idx = jnp.asarray(est_idx)
    opts = core.GAOptions(population=population, generations=generations, **options)

    def fitness_of(dg, data):
        return jnp.sum(residual(robot, data["a0"].at[idx].add(dg), data["q1"], data["q2"], data["d"]) ** 2)

    payload = dict(a0=a0, q1=jnp.asarray(q1), q2=jnp.asarray(q2), d=jnp.float64(d))
    lb, ub = -bound * jnp.ones(len(est_idx)), bound * jnp.ones(len(est_idx))
    _, init_random = core.make_init_fn(fitness_of, opts)
    state = init_random(jax.random.split(jax.random.PRNGKey(seed), 1), payload, lb, ub)
    state, best, _ = core.make_chunk_fn(fitness_of, opts, generations)(state, payload, lb, ub)
    dg, _ = jax.vmap(core.best_individual)(state)
    return a0.at[idx].add(dg[0]), np.asarray(best[0])
