"""Implementation (compensation) of a calibrated model (seed 004 §3.2, §4.4).

Given identified parameters a and desired tool positions P*, find the actuator settings q with
p(a, q) = P*: a square system for a mechanism with as many actuators as position coordinates
(the Delta). It is solved per target by Newton's method, q <- q - (dp/dq)^-1 (p(q) - P*), with
dp/dq by `jax.jacfwd` through the closure, started from the nominal inverse solution (the thesis
used Levenberg-Marquardt on the same cost; Newton on the square system converges in a few steps
from that start). Vectorised over the targets.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.forward import forward


class Compensation(NamedTuple):
    """Actuator settings q (N, n_inputs), remaining model position error |p(a, q) - P*| (N,) in m,
    and a flag per target (model error <= tol and the closure closed)."""

    q: jnp.ndarray
    error: jnp.ndarray
    ok: jnp.ndarray


@functools.partial(jax.jit, static_argnames=("robot", "steps"))
def _newton(robot, a, targets, q0, steps):
    def position(q):
        return forward(robot, a, q).p

    def one(target, q):
        def step(_, qk):
            J = jax.jacfwd(position)(qk)
            return qk - jnp.linalg.solve(J, position(qk) - target)

        q = jax.lax.fori_loop(0, steps, step, q)
        return q, jnp.linalg.norm(position(q) - target)

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
