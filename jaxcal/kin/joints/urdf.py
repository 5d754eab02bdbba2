"""URDF joints (issue 8): row = (x, y, z, roll, pitch, yaw, offset); kind = (joint type, axis).

T = Trans(xyz) Rot(rpy) Motion(axis, q + offset) with Rot(rpy) = Rz(yaw) Ry(pitch) Rx(roll) (the
URDF fixed-axis order, not the seed's PRY) and Motion a rotation about, or a slide along, the unit
axis given in the joint's own frame.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.convention import Convention, register
from jaxcal.kin.pose import Pose

URDF_ROW = ("x", "y", "z", "roll", "pitch", "yaw", "offset")
URDF_TYPES = ("revolute", "prismatic", "fixed")
_OFFSET = 6


def rpy_to_matrix(rpy):
    """URDF origin rotation: fixed-axis X-Y-Z, R = Rz(yaw) Ry(pitch) Rx(roll) (not the seed's PRY), multiplied out."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (rpy[0], rpy[1], rpy[2]) for f in (jnp.cos, jnp.sin))
    return jnp.stack([jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr]),
                      jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr]),
                      jnp.stack([-sp, cp * sr, cp * cr])])


def axis_rotation(axis, angle):
    """Rotation by `angle` about the constant unit vector `axis` (Rodrigues' formula)."""
    x, y, z = (float(c) for c in axis)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * K + (1.0 - jnp.cos(angle)) * (K @ K)


def urdf_joint(row, kind, qv) -> Pose:
    """URDF joint transform T = Trans(xyz) Rot(rpy) Motion(axis, q + offset).

    kind = (type, axis) with type "revolute" (continuous too), "prismatic" or "fixed" and axis
    a unit 3-tuple; the offset shifts the joint zero (angle or length). A revolute row may carry an
    eighth entry, a compliance k (rad/(N m)): the angle becomes q + offset + k tau with the gravity
    torque tau as a second joint input (`jaxcal.robots.urdf.with_gravity_compliance`).
    """
    joint_type, axis = kind
    R0 = rpy_to_matrix(row[3:6])
    if joint_type == "revolute":
        angle = qv[0] + row[6]
        if len(row) == 8:  # gravity compliance: qv[1] is the gravity torque, row[7] the compliance
            angle = angle + row[7] * qv[1]
        return Pose(R0 @ axis_rotation(axis, angle), row[0:3])
    if joint_type == "prismatic":
        return Pose(R0, row[0:3] + R0 @ (np.asarray(axis, float) * (qv[0] + row[6])))
    if joint_type == "fixed":
        return Pose(R0, row[0:3])
    raise ValueError(f"unknown URDF joint type {joint_type!r}; expected one of {URDF_TYPES}")


def urdf_twists(row, kind, frame: Pose) -> jnp.ndarray:
    """The parent-frame twists (omega, v) (8, 6) of the inputs (x, y, z, roll, pitch, yaw, offset, joint variable)
    of frame = `urdf_joint(row, kind, qv)` (a fixed joint: 7 rows; `Convention.local_twists`), in closed form: x, y, z
    slide along the parent's axes; yaw, pitch and roll turn about z, Rz(yaw) y and Rz(yaw) Ry(pitch) x through
    o = (x, y, z) (v = o x omega); the offset and the joint variable turn about (slide along) R a, a the joint axis."""
    joint_type, axis = kind
    o, pitch, yaw = row[0:3], row[4], row[5]
    cp, sp, cy, sy = jnp.cos(pitch), jnp.sin(pitch), jnp.cos(yaw), jnp.sin(yaw)
    zero = jnp.zeros_like(cp)

    def turn(w):
        return jnp.concatenate([w, jnp.cross(o, w)])

    def slide(u):
        return jnp.concatenate([jnp.zeros_like(u), u])

    unit = jnp.eye(3, dtype=o.dtype)
    rows = [slide(unit[0]), slide(unit[1]), slide(unit[2]), turn(jnp.stack([cy * cp, sy * cp, -sp])),
            turn(jnp.stack([-sy, cy, zero])), turn(jnp.stack([zero, zero, zero + 1.0]))]
    moving = frame.R @ np.asarray(axis, float)  # R0 Rot(a, angle) a = R0 a
    motion = {"revolute": turn, "prismatic": slide}.get(joint_type, lambda u: jnp.zeros(6, u.dtype))(moving)
    rows += [motion] if joint_type == "fixed" else [motion, motion]
    return jnp.stack(rows)


class UrdfJoints(Convention):
    """URDF joints: the joint variable adds to the offset and moves along the joint's own axis.
    A compliant revolute joint takes the gravity torque as an extra input (not counted by n_inputs)."""

    name = "urdf"
    row_names = URDF_ROW
    kinds = tuple((t, (0.0, 0.6, 0.8)) for t in URDF_TYPES)
    file_format = "urdf"

    def local_transform(self, row, kind, qv) -> Pose:
        return urdf_joint(row, kind, qv)

    def local_twists(self, row, kind, qv, frame: Pose):
        if row.shape[0] != len(URDF_ROW):  # a compliant joint (`urdf_joint`): by forward mode
            return super().local_twists(row, kind, qv, frame)
        return urdf_twists(row, kind, frame)

    def n_inputs(self, kind) -> int:
        return 0 if kind[0] == "fixed" else 1

    def is_prismatic(self, kind) -> bool:
        return kind[0] == "prismatic"

    def joint_row_index(self, kind) -> int | None:
        return None if kind[0] == "fixed" else _OFFSET

    def joint_axis(self, kind) -> np.ndarray:
        return np.asarray(kind[1], float)


register(UrdfJoints())
