"""Mobility and constraint analysis of a closed mechanism (seed 004 §2.5, eq 2.88-2.97 and §2.5.2).

The closure constraints linearised at a closed configuration, dv/da da = 0 (eq 2.90), are taken over
the full parameter set in which each free joint variable stands in for its own offset parameter,
the row entry its variable adds to (`Convention.joint_row_index`: a3 of a rotary, d3 of a prismatic
MCPC joint, phi of a planar joint; appended when the offset is not a parameter). With r the number
of significant singular values of dv/da and n_f the number of free joints: r > n_f over-constrained,
r = n_f properly constrained, r < n_f under-constrained. The null space N (last n - r right singular
vectors) post-multiplied by psi^-1, psi the rows of N of the controlled parameters (eq 2.94), gives
the closed-loop motions; a large cond(psi) marks a near-singular configuration.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.closure.core import checked_closure, closure_residual, solve
from jaxcal.kin.model import Robot, joint_variables

VERDICTS = ("proper", "over-constrained", "under-constrained")


class Mobility(NamedTuple):
    singular_values: np.ndarray  # of dv/da, descending
    r: int  # number of significant singular values
    n_free: int
    verdict: str  # one of VERDICTS
    cond_psi: float  # condition number of psi (inf when psi is singular or not square)
    near_singular: bool  # cond_psi > cond_limit
    columns: tuple[str, ...]  # names of the columns of dv/da (free joints named "theta.j{i}")
    free_rows: tuple[int, ...]  # indices of the free-joint columns in `columns`
    n_psi: np.ndarray | None  # N psi^-1 (n x (n - r)) when psi is square, else None
    actuator_motion: np.ndarray  # |d theta_free / d offset of each actuator| (0: the actuator moves nothing)


def _offset_index(robot: Robot, body_number: int) -> int:
    """Parameter index of the joint-variable offset of a body (-1 when it is not a parameter)."""
    b = robot.bodies[body_number - 1]
    k = b.conv.joint_row_index(b.kind)
    return -1 if k is None else b.rows[k]


def constraint_jacobian(robot: Robot, a, q, theta_free):
    """dv/da over the parameters with free joints in place of their offsets (eq 2.81, 2.90).

    Returns (J, column names, indices of the free-joint columns).
    """
    c = checked_closure(robot)
    a = jnp.asarray(a, dtype=jnp.float64)
    qj = joint_variables(robot, a, jnp.asarray(q, dtype=jnp.float64))
    theta_free = jnp.asarray(theta_free, dtype=jnp.float64)
    Ja = np.asarray(jax.jacfwd(lambda a_: closure_residual(robot, a_, qj, theta_free))(a))
    Jt = np.asarray(jax.jacfwd(lambda t: closure_residual(robot, a, qj, t))(theta_free))
    offsets = {_offset_index(robot, b): k for k, b in enumerate(c.free)}
    cols, names, free_rows = [], [], []
    for i, name in enumerate(robot.names):
        if i in offsets:
            free_rows.append(len(cols))
            cols.append(Jt[:, offsets[i]])
            names.append(f"theta.j{c.free[offsets[i]]}")
        else:
            cols.append(Ja[:, i])
            names.append(name)
    for k, b in enumerate(c.free):
        if _offset_index(robot, b) < 0:
            free_rows.append(len(cols))
            cols.append(Jt[:, k])
            names.append(f"theta.j{b}")
    return np.stack(cols, axis=1), tuple(names), tuple(free_rows)


def mobility(robot: Robot, a=None, q=None, theta_free=None, rtol: float = 1e-8, cond_limit: float = 1e8) -> Mobility:
    """Constraint verdict and conditioning at one closed configuration (default: nominal a, home q).

    theta_free defaults to the closure from the robot's start; give it for mechanisms that do not
    close from the start (e.g. over-constrained ones at a consistent setting).
    """
    c = checked_closure(robot)
    a = robot.nominal if a is None else jnp.asarray(a, dtype=jnp.float64)
    q = robot.home if q is None else jnp.asarray(q, dtype=jnp.float64)
    if theta_free is None:
        sol = solve(robot, a, q)
        if not bool(sol.ok):
            raise ValueError(f"robot {robot.name!r}: loops do not close at q = {np.asarray(q)} "
                             f"(|v| = {float(sol.residual_norm):.3g}); give theta_free of a closed configuration")
        theta_free = sol.theta_free
    J, names, free_rows = constraint_jacobian(robot, a, q, theta_free)
    n = J.shape[1]
    _, s, Vt = np.linalg.svd(J)
    r = int(np.sum(s > rtol * max(s[0], 1e-300))) if s.size else 0
    nf = c.n_free
    verdict = VERDICTS[0] if r == nf else VERDICTS[1] if r > nf else VERDICTS[2]
    controlled = [i for i in range(n) if i not in free_rows]
    N = Vt[r:].T
    psi = N[controlled]
    cond_psi, n_psi = np.inf, None
    if psi.shape[0] == psi.shape[1] and psi.size:
        cond_psi = float(np.linalg.cond(psi))
        if np.isfinite(cond_psi) and cond_psi < 1e15:
            n_psi = N @ np.linalg.inv(psi)
    actuator_motion = np.full(robot.n_inputs, np.nan)
    if n_psi is not None:
        for k, b in enumerate(robot.bodies):
            offset = _offset_index(robot, k + 1)  # an actuator's offset column keeps its index in a
            if b.inputs and offset >= 0:
                actuator_motion[b.inputs[0]] = float(np.linalg.norm(n_psi[list(free_rows), controlled.index(offset)]))
    return Mobility(s, r, nf, verdict, cond_psi, bool(cond_psi > cond_limit), names, free_rows, n_psi, actuator_motion)
