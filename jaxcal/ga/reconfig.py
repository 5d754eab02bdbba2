"""Reconfiguration of modular robots: snap points and the path matrix (seed 000 §7.1-7.2).

A module keeps its own parameters (body vector and orientation set-up, "jk.*") and its own joint
input (column k of q) wherever it is connected, so a calibration of the modules carries over to
any connection order. The path matrix T (eq 7.3-7.4) has T[i, j] = 1 when joint i lies on the
route from the base to body j; re-ordering it into upper-triangular form (eq 7.5) gives the true
sequence, and the snap points follow from the body vectors by S = T^T H (eq 7.6-7.8).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.model import Robot, frames


def path_matrix(order):
    """T (n, n) for modules connected base -> tip in `order` (module numbers 0..n-1), eq 7.3-7.4:
    rows are joints, columns bodies, T[i, j] = 1 if joint i is on the route to body j."""
    order = [int(k) for k in order]
    n = len(order)
    if sorted(order) != list(range(n)):
        raise ValueError(f"order {order} must be a permutation of 0..{n - 1}")
    pos = np.empty(n, int)
    pos[order] = np.arange(n)
    return (pos[:, None] <= pos[None, :]).astype(int)


def true_sequence(T):
    """The connection order encoded by a path matrix (eq 7.5): sorting the joints by the number of
    bodies they move (row sums, descending) makes T upper triangular with ones above the diagonal."""
    T = np.asarray(T, int)
    order = list(np.argsort(-T.sum(axis=1), kind="stable"))
    P = T[np.ix_(order, order)]
    if not np.array_equal(P, np.triu(np.ones_like(P))):
        raise ValueError(f"not the path matrix of a serial chain:\n{T}")
    return order


def reorder(robot: Robot, order) -> Robot:
    """The same modules (parameters and joint inputs unchanged) connected base -> tip in `order`
    (Figure 7.2b). Only the parent of each body changes, so `a` and `q` keep their layout."""
    order = [int(k) for k in order]
    true_sequence(path_matrix(order))  # validates the permutation
    if any(b.parent not in (i - 1,) for i, b in enumerate(robot.bodies)):
        raise ValueError(f"robot {robot.name!r} is not a serial chain of modules")
    bodies = tuple(dataclasses.replace(robot.bodies[k], parent=i - 1) for i, k in enumerate(order))
    name = f"{robot.name}[{'-'.join(str(k + 1) for k in order)}]"
    return dataclasses.replace(robot, bodies=bodies, tip=len(bodies) - 1, name=name)


def snap_points(robot: Robot, a, q):
    """World positions of the snap points s_1..s_n (the end of each module, eq 7.1-7.2), in the
    true sequence of `robot` (..., n, 3)."""
    return frames(robot, a, q).p


def body_vectors(robot: Robot, a, q):
    """Global body vectors h_k = s_k - s_{k-1} of each body, in the order of `robot.bodies` (..., n, 3)."""
    s = snap_points(robot, a, q)
    s0 = jnp.broadcast_to(robot.base.p, s[..., :1, :].shape)
    return s - jnp.concatenate([s0, s[..., :-1, :]], axis=-2)


def snap_points_from_path(T, H, base):
    """Eq 7.6: s_j = base + sum_i T[i, j] h_i with H (n, 3) indexed by module number."""
    return base + jnp.asarray(T, H.dtype).T @ H
