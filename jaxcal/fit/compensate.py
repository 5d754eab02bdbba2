"""Implementation (compensation) of a calibrated model (seed 004 §3.2, §4.4).

Given identified parameters a and desired tool positions P*, find the actuator settings q with
p(a, q) = P*: a square system for a mechanism with as many actuators as position coordinates
(the Delta). It is solved per target by Newton's method, q <- q - (dp/dq)^-1 (p(q) - P*), with
dp/dq by `jax.jacfwd` through the closure, started from the nominal inverse solution (the thesis
used Levenberg-Marquardt on the same cost; Newton on the square system converges in a few steps
from that start). Vectorised over the targets.

For other tasks (the Kiwibot's orientation with a strut-length bias, §4.3) `least_squares` solves one
target's non-square problem by Gauss-Newton, and `line_search` is the thesis' fast approximate method
(one steepest-descent line minimisation by quadratic interpolation, §3.2/§4.4.4); see
docs/seed004-compensation.md.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.autodiff import value_and_jacfwd
from jaxcal.forward import forward
from jaxcal.loops import varying_with


class Compensation(NamedTuple):
    """Actuator settings q (N, n_inputs), remaining model position error |p(a, q) - P*| (N,) in m,
    and a flag per target (model error <= tol and the closure closed)."""

    q: jnp.ndarray
    error: jnp.ndarray
    ok: jnp.ndarray


@functools.partial(jax.jit, static_argnames=("robot", "steps"))
def _newton(robot, a, targets, q0, steps):
    """`steps` Newton steps per target, then the error at the last iterate. The forward kinematics (a closure solve)
    is traced once: the loop runs steps + 1 turns, each evaluating p and dp/dq together at its iterate, and the last
    one only records |p - target| (`value_and_jacfwd`; with the separate p(q) of each step and the error's after the
    loop, the Delta's program took 21.3 s to compile at LLVM level 0 instead of 10.0 s, for the same settings to the
    bit)."""

    def position(q):
        return forward(robot, a, q).p

    def one(target, q):
        def step(i, carry):
            qk, _ = carry
            p, J = value_and_jacfwd(position, qk)
            moved = qk - jnp.linalg.solve(J, p - target)
            return jnp.where(i < steps, moved, qk), jnp.linalg.norm(p - target)

        return jax.lax.fori_loop(0, steps + 1, step, varying_with(q, (q, jnp.zeros((), q.dtype))))

    return jax.vmap(one)(targets, q0)


def compensate(robot, a, targets, start, steps: int = 6, tol: float = 1e-9) -> Compensation:
    """Actuator settings that put the tool of `robot` with parameters `a` on `targets` (N, 3).

    start: (N, n_inputs) initial settings, e.g. the nominal inverse solution
    (`jaxcal.closure.delta.inverse` for the Delta). The robot must have exactly 3 inputs.
    """
    targets = jnp.atleast_2d(jnp.asarray(targets, dtype=jnp.float64))
    start = jnp.atleast_2d(jnp.asarray(start, dtype=jnp.float64))
    if robot.n_inputs != 3:
        raise ValueError(f"compensate: robot {robot.name!r} has {robot.n_inputs} inputs; position compensation needs 3")
    if targets.shape[-1] != 3 or start.shape != (targets.shape[0], robot.n_inputs):
        raise ValueError(f"compensate: targets must be (N, 3) and start (N, {robot.n_inputs}); got {targets.shape}, {start.shape}")
    q, err = _newton(robot, jnp.asarray(a, dtype=jnp.float64), targets, start, steps)
    return Compensation(q, err, jnp.isfinite(err) & (err <= tol))


def least_squares(residual, q0, steps: int = 8, damping: float = 1e-12):
    """Exact implementation for a non-square task (seed 004 §3.2, eq 3.6; §4.3 for the Kiwibot):
    actuator settings minimising 1/2 |r(q)|^2 by Gauss-Newton, q <- q - (J^T J + lambda I)^-1 J^T r
    with J = dr/dq by `jax.jacfwd` and a tiny lambda that only guards a singular J^T J. One target:
    residual(q) -> r (m,), q0 (n,); vmap it over targets. The thesis used Levenberg-Marquardt on the
    same cost; from the nominal inverse solution the undamped steps converge in a few iterations."""

    def step(_, q):
        r, J = value_and_jacfwd(residual, q)
        return q - jnp.linalg.solve(J.T @ J + damping * jnp.eye(q.shape[0]), J.T @ r)

    return jax.lax.fori_loop(0, steps, step, jnp.asarray(q0, dtype=jnp.float64))


def line_search(residual, q0):
    """The thesis' fast approximate implementation (seed 004 §3.2 after eq 3.6, §4.4.4): one line
    minimisation of f(q) = 1/2 |r(q)|^2 along the steepest-descent direction d = -J^T r(q0), by
    quadratic interpolation of f at three offsets t = 0, s, 2s: the vertex
    t* = s (3 f0 - 4 f1 + f2) / (2 (f0 - 2 f1 + f2)), clipped to [0, 2s], is the step; where the
    samples are not convex the best sample is taken. s = f0 / |J^T r0|^2, the step at which f's
    first-order model along d reaches 0 (scale-free; the thesis does not state its offsets).
    One Jacobian and two extra residual evaluations per target, against ~10 of each for the exact
    solution. Returns q0 + t* d for one target; vmap it over targets."""
    q0 = jnp.asarray(q0, dtype=jnp.float64)
    r0, J = value_and_jacfwd(residual, q0)
    d = -J.T @ r0
    f0 = 0.5 * jnp.dot(r0, r0)
    s = f0 / jnp.maximum(jnp.dot(d, d), 1e-300)
    f1, f2 = (0.5 * jnp.sum(residual(q0 + t * d) ** 2) for t in (s, 2.0 * s))
    curvature = f0 - 2.0 * f1 + f2
    vertex = jnp.clip(s * (3.0 * f0 - 4.0 * f1 + f2) / (2.0 * jnp.where(curvature > 0, curvature, 1.0)), 0.0, 2.0 * s)
    best = jnp.array([0.0, s, 2.0 * s])[jnp.argmin(jnp.array([f0, f1, f2]))]
    return q0 + jnp.where(curvature > 0, vertex, best) * d
