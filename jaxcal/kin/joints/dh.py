"""Denavit-Hartenberg tables as users copy them: standard (distal) DH and Craig's modified DH.

Standard DH (Denavit & Hartenberg 1955; the layout of most vendor sheets, e.g. UR, KUKA, ABB):
row = (theta, d, a, alpha, beta),

    T = Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta),
    R = Rz(theta) Rx(alpha) Ry(beta),   p = (a cos theta, a sin theta, d).

Frame i sits at the distal end of link i; joint i turns about (or slides along) the z axis of the
*parent* frame i-1, through the parent's origin. The kind is sigma as in seed 001: 0 revolute (the
joint variable adds to theta), 1 prismatic (adds to d), 2 a constant frame. beta is Hayati's
rotation about the new y axis (Hayati & Mirmirani 1985) for nearly parallel consecutive axes; it is 0
in a plain DH table.

Craig's modified DH (Craig 2005, ch. 3): row = (alpha, a, theta, d, beta),

    T = Ry(beta) Rx(alpha) Tx(a) Rz(theta) Tz(d),

the same transform as Khalil-Kleinfinger's (`jaxcal.kin.joints.mdh`, letters alpha d theta r) with
Craig's letters: a along x, d along z. A separate registered name keeps the parameter names and the
written table in the letters the user gave.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.convention import Convention, pose_matrix, register
from jaxcal.kin.joints.mdh import ModifiedDH, mdh_frame
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import rot_x, rot_y, rot_z

DH_ROW = ("theta", "d", "a", "alpha", "beta")
CRAIG_ROW = ("alpha", "a", "theta", "d", "beta")
_THETA, _D = 0, 1


def dh_frame(row, sigma: int, qv) -> Pose:
    """Standard DH T = Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta); qv = (joint variable,) or ().

    sigma 0: theta -> theta + q; sigma 1: d -> d + q; sigma 2: no joint. The rotation is multiplied out (`mdh_frame`)."""
    theta, d, a, alpha, beta = row
    if sigma == 0:
        theta = theta + qv[0]
    elif sigma == 1:
        d = d + qv[0]
    ct, st, ca, sa, cb, sb = (f(a) for a in (theta, alpha, beta) for f in (jnp.cos, jnp.sin))
    R = jnp.stack([jnp.stack([cb * ct - sb * st * sa, -st * ca, sb * ct + cb * st * sa]),
                   jnp.stack([cb * st + sb * ct * sa, ct * ca, sb * st - cb * ct * sa]),
                   jnp.stack([-sb * ca, sa, cb * ca])])
    p = jnp.stack([a * jnp.cos(theta), a * jnp.sin(theta), d])
    return Pose(R, p)


def craig_frame(row, sigma: int, qv) -> Pose:
    """Craig modified DH T = Ry(beta) Rx(alpha) Tx(a) Rz(theta) Tz(d) (Khalil-Kleinfinger with d -> a, r -> d)."""
    alpha, a, theta, d, beta = row
    return mdh_frame(jnp.stack([alpha, a, theta, d, beta]), sigma, qv)


class StandardDH(Convention):
    """Standard (distal) DH: the joint moves first, about the parent's z through the parent's origin."""

    name = "standard_dh"
    row_names = DH_ROW
    kinds = (0, 1, 2)

    def local_transform(self, row, kind, qv) -> Pose:
        return dh_frame(row, kind, qv)

    def n_inputs(self, kind) -> int:
        return 1 if kind in (0, 1) else 0

    def is_prismatic(self, kind) -> bool:
        return kind == 1

    def joint_row_index(self, kind) -> int | None:
        return {0: _THETA, 1: _D}.get(kind)

    def axis_through_parent_origin(self, kind) -> bool:
        return True

    def axis_in_parent_frame(self, kind) -> bool:
        return True

    def motion_split(self, row, kind):
        """T = A M(q) B with B = Tx(a) Rx(alpha) Ry(beta) and A = Tz(d) Rz(theta) (revolute: Rz commutes
        with Tz) or Rz(theta) Tz(d) (prismatic); a constant row is A = T, B = I. The URDF joint origins
        this gives are those of the UR description (shoulder at z = d1, elbow at x = a2, ...)."""
        theta, d, a, alpha, beta = (float(v) for v in row)
        if kind == 2:
            return pose_matrix(dh_frame(np.array([theta, d, a, alpha, beta]), 2, ())), np.eye(4)
        A = np.eye(4)
        A[:3, :3], A[2, 3] = np.asarray(rot_z(theta)), d
        B = np.eye(4)
        B[:3, :3], B[0, 3] = np.asarray(rot_x(alpha) @ rot_y(beta)), a
        return A, B


class CraigMDH(ModifiedDH):
    """Craig's modified DH: the Khalil-Kleinfinger transform with Craig's letters (a along x, d along z)."""

    name = "craig_mdh"
    row_names = CRAIG_ROW

    def local_transform(self, row, kind, qv) -> Pose:
        return craig_frame(row, kind, qv)

    def joint_row_index(self, kind) -> int | None:
        return {0: 2, 1: 3}.get(kind)


register(StandardDH())
register(CraigMDH())
