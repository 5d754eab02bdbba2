"""The joint-convention interface and its registry.

A convention says how one body's parameter row and joint values give the body's frame in its
parent's frame, T = local_transform(row, kind, qv), and answers the questions other modules ask
about a joint (is it prismatic, which axis does it move along, which row entry does its variable
offset). `Body.convention` names a registered convention; `Body.conv` is the object. A new
convention is one module in `jaxcal.kin.joints` (imported, hence registered, with the package) or,
outside the package, any subclass instance passed to `register`.
"""

from __future__ import annotations

import abc

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.pose import Pose

Z_AXIS = (0.0, 0.0, 1.0)

_REGISTRY: dict[str, "Convention"] = {}


class Convention(abc.ABC):
    """One parametrisation of a body's local transform.

    Class attributes:
        name: registry key (the `Body.convention` string).
        row_names: names of the entries of one body's parameter row.
        kinds: the joint kinds it accepts (for kinds that carry data, such as a URDF axis, one
            example per joint type).
        file_format: "yaml" (seed-table robot file) or "urdf": how a calibrated robot is written.
        reads_parent: False for the usual parent-relative joints. True when joint angles are
            absolute (measured from the base): the evaluator then passes the parent's row and
            joint values in front of the body's own, local_transform(parent_row ++ row, kind,
            parent_qv ++ qv), zeros for a body on the base.
    """

    name: str
    row_names: tuple[str, ...]
    kinds: tuple
    file_format: str = "yaml"
    reads_parent: bool = False

    @abc.abstractmethod
    def local_transform(self, row, kind, qv) -> Pose:
        """The body's frame in its parent's frame for parameter row `row` and joint values `qv`."""

    def local_twists(self, row, kind, qv, frame: Pose):
        """The twists (omega, v) (k, 6), in the parent frame, of the k = len(row) + len(qv) inputs of the local frame
        `frame` = local_transform(row, kind, qv): (dT T^-1)^vee per input, [omega]_x = dR R^T, v = dp - omega x p
        (`jaxcal.kin.twists`). Here by forward mode; a convention may give them in closed form."""
        u = jnp.concatenate([row, qv])
        n = row.shape[0]
        _, (dR, dp) = jax.vmap(lambda e: jax.jvp(lambda v: self.local_transform(v[:n], kind, v[n:]), (u,), (e,)))(
            jnp.eye(u.shape[0], dtype=u.dtype))
        R = frame.R
        omega = jnp.stack([dR[:, 2] @ R[1], dR[:, 0] @ R[2], dR[:, 1] @ R[0]], axis=-1)  # (W21, W02, W10), W = dR R^T
        return jnp.concatenate([omega, dp - jnp.cross(omega, frame.p)], axis=-1)

    @abc.abstractmethod
    def n_inputs(self, kind) -> int:
        """How many joint variables a body of this kind consumes."""

    @abc.abstractmethod
    def is_prismatic(self, kind) -> bool:
        """True when the (first) joint variable is a length along the joint axis."""

    @abc.abstractmethod
    def joint_row_index(self, kind) -> int | None:
        """Index in the row of the entry the (first) joint variable adds to; None for a fixed body."""

    def is_fixed(self, kind) -> bool:
        """True when the local transform takes no joint variable (a constant frame)."""
        return self.n_inputs(kind) == 0

    def is_revolute(self, kind) -> bool:
        """True when the (first) joint variable is an angle about the joint axis."""
        return not self.is_fixed(kind) and not self.is_prismatic(kind)

    def joint_axis(self, kind) -> np.ndarray:
        """Unit vector of the joint motion in the body's own frame (z unless the convention says otherwise)."""
        return np.array(Z_AXIS)

    def axis_through_parent_origin(self, kind) -> bool:
        """True when the joint axis passes through the parent's origin instead of the body's own."""
        return False

    def axis_in_parent_frame(self, kind) -> bool:
        """True when `joint_axis` is expressed in the parent's frame rather than the body's own (a joint
        that moves first, before the body's constant geometry, as in standard DH: the axis is the
        parent's z whatever the row). Use `joint_line` to get the axis in the world either way."""
        return False

    def motion_split(self, row, kind):
        """(A, B), constant 4x4 numpy matrices with local_transform(row, kind, q) = A M(q) B, M(q) the
        rotation about (revolute) or slide along (prismatic) `joint_axis(kind)` through the origin.

        Used to write a robot as URDF (joint origin = B_parent A, axis = joint_axis). The default,
        A = T(row, kind, 0) and B = I, holds for joints that move last, about the body's own axis
        through its own origin (modified DH, URDF); conventions where that is not so override it."""
        if self.axis_through_parent_origin(kind) or self.axis_in_parent_frame(kind):
            raise NotImplementedError(f"convention {self.name!r} must override motion_split")
        return pose_matrix(self.local_transform(row, kind, np.zeros(self.n_inputs(kind)))), np.eye(4)


def pose_matrix(pose: Pose) -> np.ndarray:
    """The 4x4 numpy matrix of a Pose."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(pose.R, float), np.asarray(pose.p, float)
    return T


def joint_line(conv: Convention, kind, R_body, p_body, R_parent, p_parent):
    """(point, direction) of a one-input joint's axis in the world, from the body's and its parent's
    world frames: the direction is R_body u (R_parent u when `axis_in_parent_frame`), u = joint_axis(kind);
    the point is the body's origin, or the parent's when `axis_through_parent_origin`."""
    u = conv.joint_axis(kind)
    direction = (R_parent if conv.axis_in_parent_frame(kind) else R_body) @ u
    point = p_parent if conv.axis_through_parent_origin(kind) else p_body
    return point, direction


def register(convention: Convention) -> Convention:
    """Add a convention under `convention.name`; a name already taken by another class is an error."""
    known = _REGISTRY.get(convention.name)
    if known is not None and type(known) is not type(convention):
        raise ValueError(f"convention {convention.name!r} is already registered by {type(known).__name__}")
    _REGISTRY[convention.name] = convention
    return convention


def get_convention(name: str) -> Convention:
    """The registered convention called `name`."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown convention {name!r}; registered: {sorted(_REGISTRY)}") from None


def registered() -> tuple[str, ...]:
    """Names of every registered convention."""
    return tuple(sorted(_REGISTRY))
