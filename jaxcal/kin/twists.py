"""The tool frames of an open tree and the first-order motion of each per robot parameter, from one forward pass.

A change du of body b's inputs u_b = (parameter row, joint values) moves b's local frame L_b by dL_b, and with it
every frame below b by the same rigid motion. In the world that motion is the twist (spatial velocity)

    xi = Ad(W_p) (dL_b L_b^-1)^vee,   W_p = (R_p, p_p) the parent's world frame,
    (dL L^-1)^vee = (omega, dp - omega x p)  with  [omega]_x = dR R^T,   Ad(W) (omega, v) = (R omega, R v + p x R omega),

and a tool frame T = (R_T, p_T) below b moves by dR_T = [omega]_x R_T, dp_T = omega x p_T + v (the product of
exponentials' Jacobian, Lynch & Park, "Modern Robotics", 2017, §5.1, with the parameters of seed 001 eq 2-4 in place
of the joints). Each convention gives its inputs' twists in the parent frame (`Convention.local_twists`: closed
form for modified DH, URDF and one-axis PRY modules, forward mode otherwise). Joint variables depend on the
parameters through the gains only (seed 001 eq 4, q_j = Cj diag(K) Cm q_m): d q_j / d K by forward mode, times the
twists of the inputs that read q_j. Gathered per parameter and per tip (bodies off a tip's path do not move it), the
twists make Xi (n_tips, P, 6); a reading's Jacobian is then its derivative along the 6 unit twists of each tool
(`wrench`) times Xi (`jaxcal.fit.core.open_residual_and_jacobian`), in place of m reverse passes through the chain.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.model import Robot, body_frames, joint_variables, take
from jaxcal.kin.pose import Pose


def _own_inputs(robot: Robot, b: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Body b's own parameter indices and joint-variable indices (-1: a constant 0)."""
    body = robot.bodies[b]
    return tuple(body.rows), tuple(body.inputs) if body.inputs else (-1,) * body.conv.n_inputs(body.kind)


def _body_inputs(robot: Robot, b: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(parameter indices, joint-variable indices) of body b's local transform inputs, in the order the forward pass
    gives them (`jaxcal.kin.model.body_frames`: a convention that `reads_parent` takes its parent's first)."""
    rows, joints = _own_inputs(robot, b)
    body = robot.bodies[b]
    if body.conv.reads_parent:
        up_rows, up_joints = _own_inputs(robot, body.parent) if body.parent >= 0 else ((-1,) * len(rows), (-1,) * len(joints))
        rows, joints = up_rows + rows, up_joints + joints
    return rows, joints


def _path(robot: Robot, b: int) -> set[int]:
    """b and every body above it."""
    out = set()
    while b >= 0:
        out.add(b)
        b = robot.bodies[b].parent
    return out


def _joint_count(robot: Robot) -> int:
    """How many joint variables q_j = Cj diag(K) Cm q_m there are (seed 001 eq 4): Cj's rows, else one per input."""
    for matrix in (robot.coupling_joint, robot.coupling_motor):
        if matrix is not None:
            return np.shape(matrix)[0]
    return robot.n_inputs


def _width(robot: Robot) -> int:
    """The most inputs of a body: each body's input twists take that many rows (the rest 0)."""
    return max(sum(map(len, _body_inputs(robot, b))) for b in range(len(robot.bodies)))


def _levels(sources: list[list[int]]) -> tuple[tuple[int, ...], ...]:
    """Index tuples, one per level l, of each entry's l-th source (-1 past its last); at least one level."""
    depth = max([len(s) for s in sources] + [1])
    return tuple(tuple(s[level] if level < len(s) else -1 for s in sources) for level in range(depth))


@functools.lru_cache(maxsize=64)
def assembly(robot: Robot) -> tuple[tuple, tuple, tuple[int, ...]]:
    """Static maps over the body inputs, body b's input i at k = b * `_width` + i: (joint_sources, param_sources,
    gains).

    joint_sources[t][l][j]: the l-th input on tip t's path that reads joint variable j (-1: none), so that q_j's twist
    is the sum over l; param_sources[t][l][i]: the l-th source of parameter i, a body input k < K or K + g for the g-th
    gain (-1: none). Most parameters have one source; a row that two bodies read (`reads_parent`) has two.
    gains: `Robot.gains` (the parameter index of each input's gain, -1 none), () without gains."""
    tips = robot.tips or (robot.tip,)
    n_b = len(robot.bodies)
    inputs = [_body_inputs(robot, b) for b in range(n_b)]
    width = _width(robot)
    K = n_b * width
    gains = tuple(robot.gains) if robot.gains is not None else ()
    joint_sources, param_sources = [], []
    for tip in tips:
        path = _path(robot, tip % n_b)
        by_joint = [[] for _ in range(_joint_count(robot))]
        by_param = [[] for _ in range(robot.n_params)]
        for b, (rows, joints) in enumerate(inputs):
            for slot, (index, by) in enumerate([(i, by_param) for i in rows] + [(j, by_joint) for j in joints]):
                if b in path and index >= 0:
                    by[index].append(b * width + slot)
        for g, i in enumerate(gains):
            if i >= 0:
                by_param[i].append(K + g)
        joint_sources.append(_levels(by_joint))
        param_sources.append(_levels(by_param))
    return tuple(joint_sources), tuple(param_sources), gains


def _summed(rows, levels):
    """sum over the levels of take(rows, level) (`jaxcal.kin.model.take`: static slices, no gather)."""
    out = take(rows, levels[0])
    for level in levels[1:]:
        out = out + take(rows, level)
    return out


def _times(A, B):
    """A @ B for a few rows and columns, as a product summed (XLA:CPU fuses it; a dot is a kernel call of its own)."""
    return jnp.sum(A[:, :, None] * B[None], axis=1)


def _world_twists(xi, parents: Pose):
    """Parent-frame twists xi (n_b, k, 6) of every body's inputs in the world, parents (n_b, 3, 3)/(n_b, 3) the
    bodies' parents' world frames: Ad(parent) (omega, v) = (R omega, R v + p x R omega)."""
    omega_w = jnp.einsum("bij,bkj->bki", parents.R, xi[..., :3])
    v_w = jnp.einsum("bij,bkj->bki", parents.R, xi[..., 3:]) + jnp.cross(parents.p[:, None, :], omega_w)
    return jnp.concatenate([omega_w, v_w], axis=-1)


def tools_and_twists(robot: Robot, a, q, held=False):
    """(tools, Xi) for one joint-input vector q (n_inputs,) of an open tree: the tool frames (tips: (K, 3, 3)/(K, 3),
    else (3, 3)/(3,)), as `jaxcal.kin.model.forward_open`, and the world twist (omega, v) of each tool per robot
    parameter, Xi (n_tips, P, 6) (module docstring). held (traced): Xi = 0, not computed."""
    steps = body_frames(robot, a, joint_variables(robot, a, q))
    worlds = [world for *_, world in steps]
    inputs = [(row, qv, local, parent) for row, qv, local, parent, _ in steps]
    at = [t % len(robot.bodies) for t in (robot.tips or (robot.tip,))]
    if robot.tips:
        tools = Pose(jnp.stack([worlds[t].R for t in at]), jnp.stack([worlds[t].p for t in at]))
    else:
        tools = worlds[at[0]]
    Xi = jax.lax.cond(held, lambda: jnp.zeros((len(at), robot.n_params, 6), a.dtype),
                      lambda: parameter_twists(robot, a, q, inputs))
    return tools, Xi


def parameter_twists(robot: Robot, a, q, inputs) -> jnp.ndarray:
    """Xi (n_tips, P, 6) from each body's (row, joint values, local frame, parent's world frame) in `inputs`: the
    bodies' input twists (`Convention.local_twists`) in the world, gathered per parameter (`assembly`); a gain's from
    d q_j / d gain (forward mode, seed 001 eq 4) times the twists of the inputs that read q_j."""
    width = _width(robot)
    local = [body.conv.local_twists(row, body.kind, qv, frame) for body, (row, qv, frame, _) in zip(robot.bodies, inputs)]
    local = jnp.stack([jnp.pad(xi, ((0, width - xi.shape[0]), (0, 0))) for xi in local])
    parents = Pose(jnp.stack([parent.R for *_, parent in inputs]), jnp.stack([parent.p for *_, parent in inputs]))
    C = _world_twists(local, parents).reshape(-1, 6)
    joint_sources, param_sources, gains = assembly(robot)
    if gains:
        at = [i for i in gains if i >= 0]
        tangents = np.zeros((len(at), robot.n_params))
        tangents[np.arange(len(at)), at] = 1.0
        dq = jax.vmap(lambda e: jax.jvp(lambda x: joint_variables(robot, x, q), (a,), (e,))[1])(jnp.asarray(tangents, a.dtype))
        row_of = np.cumsum(np.asarray(gains) >= 0) - 1  # gain g's row of dq
        slot = tuple(int(k) if i >= 0 else -1 for k, i in zip(row_of, gains))
    Xi = []
    for joints, params in zip(joint_sources, param_sources):
        sources = jnp.concatenate([C, take(_times(dq, _summed(C, joints)), slot)]) if gains else C
        Xi.append(_summed(sources, params))
    return jnp.stack(Xi)


def wrench(tool: Pose, cotangent: Pose):
    """The derivative of a scalar along the world twists (omega, v) of the frame `tool` (..., 6), from its derivative
    with respect to the frame's entries, cotangent = (G = d/dR, g = d/dp): along (omega, v) the frame moves by
    ([omega]_x R, omega x p + v), so the derivative is <G R^T, [omega]_x> + omega . (p x g) + v . g, i.e.
    (vee of M - M^T with M = G R^T, plus p x g; g)."""
    M = jnp.einsum("...ab,...cb->...ac", cotangent.R, tool.R)
    turn = jnp.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1)
    return jnp.concatenate([turn + jnp.cross(tool.p, cotangent.p), cotangent.p], axis=-1)
