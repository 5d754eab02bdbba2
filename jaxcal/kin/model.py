"""Robot description (static structure + flat parameter table) and the one tree evaluator.

A robot is a tree of bodies. Body i has a parent (-1 = the base frame), a convention (the name of a
registered `jaxcal.kin.convention.Convention`), a kind, the indices of its parameter row inside the
flat vector `a`, and the indices of the joint inputs it consumes. `frames(robot, a, q)` composes
the conventions' local transforms from the base outwards and returns every body frame;
`forward_open(robot, a, q)` returns the tool frame. Both jit and vmap; leading batch axes of `q`
are mapped over.

Parameters carry a unit kind ("length", "angle", "gain", "scale"), a free/fixed flag and a
priority (seed 001 §2.2: higher priority columns are kept first in the base set; 0 = never
identified).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxcal.kin.joints  # noqa: F401  (registers the built-in conventions)
from jaxcal.kin.convention import Convention, get_convention
from jaxcal.kin.pose import Pose

UNIT_KINDS = ("length", "angle", "gain", "scale")


@dataclasses.dataclass(frozen=True)
class Body:
    """Static description of one body/frame of the tree."""

    name: str
    convention: str  # registry name of the convention, e.g. "pry", "mdh", "mcpc", "urdf", "planar"
    kind: Any  # joint kind in that convention: PRY kind (str), MDH sigma / MCPC type (int), URDF (type, axis)
    parent: int  # index of the parent body, -1 for the base frame
    rows: tuple[int, ...]  # indices of this body's parameter row in `a`; -1 = constant zero
    inputs: tuple[int, ...] = ()  # indices into the joint-variable vector; none: the joint stays at 0

    @property
    def conv(self) -> Convention:
        """The registered convention object named by `convention`."""
        return get_convention(self.convention)


@dataclasses.dataclass(frozen=True, eq=False)
class Robot:
    """A calibratable robot. Hashes by identity so it can be a static jit argument."""

    name: str
    bodies: tuple[Body, ...]
    names: tuple[str, ...]
    nominal_np: np.ndarray
    units: tuple[str, ...]
    free_mask: np.ndarray
    priority: np.ndarray
    joint_names: tuple[str, ...]
    home_np: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    tip: int = -1  # body whose frame is the tool frame
    base: Pose | None = None  # constant transform from the world to the root (PRY b0)
    gains: tuple[int, ...] | None = None  # parameter index of each input's transmission gain
    coupling_joint: np.ndarray | None = None  # Cj of seed 001 eq 4
    coupling_motor: np.ndarray | None = None  # Cm of seed 001 eq 4
    closure: Any = None  # loop-closure description (jaxcal.closure); None for open chains
    extras: dict = dataclasses.field(default_factory=dict)
    tips: tuple[int, ...] = ()  # a tree read at several bodies: the tool frame of each marker slot (empty: `tip` only)

    def __post_init__(self):
        if self.tips and self.closure is not None:
            raise ValueError(f"robot {self.name!r}: several tips (tips=) are for open trees, not closed mechanisms")
        bad = [t for t in self.tips if not -len(self.bodies) <= t < len(self.bodies)]
        if bad:
            raise ValueError(f"robot {self.name!r}: tips {bad} are not body indices (0..{len(self.bodies) - 1})")

    @property
    def n_tips(self) -> int:
        """Number of tool frames `forward` returns per sample: len(tips), or 1 for a single tool."""
        return len(self.tips) or 1

    @property
    def nominal(self) -> jnp.ndarray:
        return jnp.asarray(self.nominal_np)

    @property
    def home(self) -> jnp.ndarray:
        return jnp.asarray(self.home_np)

    @property
    def n_inputs(self) -> int:
        return len(self.joint_names)

    @property
    def n_params(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"robot {self.name!r} has no parameter {name!r}") from None

    def replace(self, **changes) -> "Robot":
        return dataclasses.replace(self, **changes)

    def with_free(self, names_or_mask) -> "Robot":
        """A copy whose free mask is the given names (or boolean mask)."""
        mask = np.asarray(names_or_mask)
        if mask.dtype != bool:
            mask = np.isin(np.array(self.names), list(names_or_mask))
        return self.replace(free_mask=mask)

    def table(self) -> str:
        """Human-readable parameter table."""
        lines = [f"{'name':<16}{'nominal':>14}  {'unit':<7}{'free':<6}{'prio':>5}"]
        for n, v, u, f, pr in zip(self.names, self.nominal_np, self.units, self.free_mask, self.priority):
            lines.append(f"{n:<16}{v:>14.6g}  {u:<7}{'yes' if f else 'no':<6}{pr:>5g}")
        return "\n".join(lines)


def joint_variables(robot: Robot, a, q):
    """Joint variables from motor readings: q_j = Cj diag(K) Cm q_m (seed 001 eq 4).

    Offsets live in the convention rows (theta/r for MDH, a3/d3 for MCPC, yaw for PRY).
    """
    qm = q
    if robot.coupling_motor is not None:
        qm = jnp.asarray(robot.coupling_motor) @ qm
    if robot.gains is not None:
        k = jnp.stack([a[i] if i >= 0 else jnp.ones((), a.dtype) for i in robot.gains])
        qm = k * qm
    if robot.coupling_joint is not None:
        qm = jnp.asarray(robot.coupling_joint) @ qm
    return qm


def take(v, index: tuple[int, ...]):
    """v[index] (along v's first axis) for a constant index tuple (-1: the constant 0), as static slices of its runs of
    consecutive entries.

    A gather's derivative in reverse mode is a scatter, which XLA:CPU runs as a loop over the indices (40 turns of 5
    kernels in the Stanford arm's residual-and-Jacobian, 10 % of it); a slice's is a pad, fused with its neighbours."""
    def continues(k):  # index[k] extends the run that index[k - 1] ends
        return index[k] == index[k - 1] == -1 or (index[k - 1] != -1 and index[k] == index[k - 1] + 1)

    pieces, start = [], 0
    for k in range(1, len(index) + 1):
        if k == len(index) or not continues(k):
            first = index[start]
            pieces.append(jnp.zeros((k - start,) + v.shape[1:], v.dtype) if first == -1 else v[first:first + k - start])
            start = k
    return jnp.concatenate(pieces) if pieces else jnp.zeros((0,) + v.shape[1:], v.dtype)


def body_row(body: Body, a_ext):
    """The body's parameter row from a_ext = (a, 0): index -1 reads the constant zero."""
    return take(a_ext, body.rows)


def body_joint_values(body: Body, qj):
    """The body's joint values from qj; a body with no inputs holds its joint variables at 0."""
    if body.inputs:
        return take(qj, body.inputs)
    return jnp.zeros(body.conv.n_inputs(body.kind), qj.dtype)


def body_frames(robot: Robot, a, qj) -> list[tuple]:
    """For each body, from the base outwards, (row, qv, local, parent, world) for one vector of joint variables qj:
    the row and joint values its convention reads (a convention that `reads_parent` gets its parent's first), its
    local transform, its parent's world frame (`robot.base` or the identity for a body on the base) and its own."""
    root = robot.base if robot.base is not None else Pose.identity()
    a_ext = jnp.append(a, 0.0)
    out, rows, qvs = [], [], []
    for body in robot.bodies:
        conv = body.conv
        row, qv = body_row(body, a_ext), body_joint_values(body, qj)
        rows.append(row)
        qvs.append(qv)
        if conv.reads_parent:  # absolute joint angles: the parent's row and values come first
            up = body.parent
            row = jnp.concatenate([rows[up] if up >= 0 else jnp.zeros_like(row), row])
            qv = jnp.concatenate([qvs[up] if up >= 0 else jnp.zeros_like(qv), qv])
        local = conv.local_transform(row, body.kind, qv)
        parent = root if body.parent < 0 else out[body.parent][4]
        out.append((row, qv, local, parent, parent.compose(local)))
    return out


def frames_single(robot: Robot, a, qj) -> Pose:
    """Every body frame in the world, for one vector of joint variables qj. Returns stacked Pose."""
    worlds = [world for *_, world in body_frames(robot, a, qj)]
    return Pose(jnp.stack([w.R for w in worlds]), jnp.stack([w.p for w in worlds]))


def map_leading_axes(fn, q):
    """Apply fn, written for one joint vector (n_inputs,), over all leading axes of q (..., n_inputs)."""
    q = jnp.asarray(q)
    if q.ndim == 1:
        return fn(q)
    lead = q.shape[:-1]
    out = jax.vmap(fn)(q.reshape((-1, q.shape[-1])))
    return jax.tree_util.tree_map(lambda x: x.reshape(lead + x.shape[1:]), out)


@functools.partial(jax.jit, static_argnums=0)
def frames(robot: Robot, a, q) -> Pose:
    """All body frames (..., n_bodies, 3, 3)/(..., n_bodies, 3) for joint inputs q (..., n_inputs)."""
    a = jnp.asarray(a, dtype=jnp.float64)

    def one(qi):
        return frames_single(robot, a, joint_variables(robot, a, qi))

    return map_leading_axes(one, jnp.asarray(q, dtype=jnp.float64))


@functools.partial(jax.jit, static_argnums=0)
def forward_open(robot: Robot, a, q) -> Pose:
    """Tool frame of an open (serial or tree) robot for one or a batch of joint inputs: (..., 3, 3)/(..., 3), or
    for a tree read at several bodies (`robot.tips`, K slots) the stacked frames (..., K, 3, 3)/(..., K, 3).
    Compiled (robot static) with the tip's slice: called from Python, the slice of `frames`' output ran op by op, one
    more compile for every robot and shape (537 of them in the test suite)."""
    f = frames(robot, a, q)
    if robot.tips:
        at = np.asarray(robot.tips)
        return Pose(f.R[..., at, :, :], f.p[..., at, :])
    return Pose(f.R[..., robot.tip, :, :], f.p[..., robot.tip, :])
