"""Joint conventions: each maps one body's parameter row and joint value to a local transform.

All three are plug-ins of the one tree evaluator in `jaxcal.kin.model`:

- PRY six-parameter module (seed 000 §3.2, eq 3.45-3.48, Table 3.3):
  row = (bx, by, bz, pitch, roll, yaw); R = Rs Rm with Rs = Rx Ry Rz(pry) and Rm the motion part
  of the joint kind; the body vector b = bs + bm is expressed after the rotation, so the local
  transform is (Rs Rm, Rs Rm b) and p_{n+1} = b0 + sum_i R_0i b_i (eq 3.43).
- Khalil-Kleinfinger modified DH with Hayati beta (seed 001 eq 2-3):
  row = (alpha, d, theta, r, beta); T = Rot(y, beta) Rot(x, alpha) Trans(x, d) Rot(z, theta) Trans(z, r);
  the joint variable adds to theta (sigma = 0) or r (sigma = 1); sigma = 2 frames are constant.
- MCPC (seed 004 §2.2, eq 2.1-2.18, 2.45): row = (a1, a2, a3, d1, d2, d3);
  T = Rx(a1) Ry(a2) Trans(d1, d2, 0) Rz(a3) Trans(0, 0, d3); the joint setting adds to a3
  (rotary) or d3 (prismatic).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import pry_to_matrix, rot_x, rot_y, rot_z

# Joint kinds of seed 000 Table 3.3 and how many joint inputs each consumes.
PRY_KINDS = {"revolute": 1, "prismatic": 1, "cylindrical": 2, "universal": 2, "spherical": 3, "fixed": 0}
PRY_ROW = ("bx", "by", "bz", "pitch", "roll", "yaw")
MDH_ROW = ("alpha", "d", "theta", "r", "beta")
MCPC_ROW = ("a1", "a2", "a3", "d1", "d2", "d3")


def pry_motion(kind: str, qv):
    """(Rm, bm) of seed 000 Table 3.3 for joint values qv (length PRY_KINDS[kind])."""
    zero3 = jnp.zeros(3, dtype=jnp.result_type(float))
    if kind == "revolute":
        return rot_z(qv[0]), zero3
    if kind == "prismatic":
        return jnp.eye(3), zero3.at[2].set(qv[0])
    if kind == "cylindrical":
        return rot_z(qv[0]), zero3.at[2].set(qv[1])
    if kind == "universal":
        return rot_z(qv[0]) @ rot_y(qv[1]), zero3
    if kind == "spherical":
        return rot_z(qv[0]) @ rot_y(qv[1]) @ rot_x(qv[2]), zero3
    if kind == "fixed":
        return jnp.eye(3), zero3
    raise ValueError(f"unknown PRY joint kind {kind!r}; expected one of {sorted(PRY_KINDS)}")


def pry_module(row, kind: str, qv) -> Pose:
    """Local transform (Rs Rm, Rs Rm (bs + bm)) of one six-parameter module."""
    Rm, bm = pry_motion(kind, qv)
    R = pry_to_matrix(row[3:6]) @ Rm
    return Pose(R, R @ (row[0:3] + bm))


def mdh_frame(row, sigma: int, qv) -> Pose:
    """Khalil-Kleinfinger frame with Hayati beta (seed 001 eq 3); qv = (joint variable,) or ()."""
    alpha, d, theta, r, beta = row
    if sigma == 0:
        theta = theta + qv[0]
    elif sigma == 1:
        r = r + qv[0]
    R = rot_y(beta) @ rot_x(alpha) @ rot_z(theta)
    p = rot_y(beta) @ (jnp.stack([d, 0.0 * d, 0.0 * d]) + rot_x(alpha) @ jnp.stack([0.0 * r, 0.0 * r, r]))
    return Pose(R, p)


def mcpc_frame(row, joint_type: int, qv) -> Pose:
    """MCPC transform (seed 004 eq 2.14-2.18); joint_type 0 rotary, 1 prismatic, 2 spherical, 3 auxiliary."""
    a1, a2, a3, d1, d2, d3 = row
    if joint_type == 0:
        a3 = a3 + qv[0]
    elif joint_type == 1:
        d3 = d3 + qv[0]
    V = rot_x(a1) @ rot_y(a2)
    R = V @ rot_z(a3)
    p = V @ jnp.stack([d1, d2, d3])
    return Pose(R, p)


# URDF joint (issue 8): row = (x, y, z, roll, pitch, yaw, offset); kind = (joint type, axis).
URDF_ROW = ("x", "y", "z", "roll", "pitch", "yaw", "offset")
URDF_TYPES = ("revolute", "prismatic", "fixed")


def rpy_to_matrix(rpy):
    """URDF origin rotation: fixed-axis X-Y-Z, R = Rz(yaw) Ry(pitch) Rx(roll) (not the seed's PRY)."""
    return rot_z(rpy[2]) @ rot_y(rpy[1]) @ rot_x(rpy[0])


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
