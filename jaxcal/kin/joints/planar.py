"""Planar bodies with absolute joint angles: the 2-D four-bar of seed 004 §2.5 (eq 2.71-2.87).

Each body j has a row (a_j, phi_j): a link length and an angle offset. Its frame has the absolute
angle psi_j = theta_j + phi_j (theta_j its joint variable, measured from the base x axis) and its
origin at the end of the parent's link, r_j = r_p + a_p (cos psi_p, sin psi_p, 0), r_j = 0 on the
base (eq 2.72-2.76). Relative to the parent frame, whose rotation is Rz(psi_p), that is
T = (Rz(psi_j - psi_p), (a_p, 0, 0)): the body reads its parent's row and joint value
(`reads_parent`), which are zero for a body on the base.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.kin.convention import Convention, register
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import rot_z

PLANAR_ROW = ("a", "phi")
_PHI = 1


def planar_link(row, qv) -> Pose:
    """T = (Rz(psi - psi_p), (a_p, 0, 0)) for row = (a_p, phi_p, a, phi), qv = (theta_p, theta)."""
    a_p, phi_p, _, phi = row
    theta_p, theta = qv
    return Pose(rot_z((phi + theta) - (phi_p + theta_p)), jnp.stack([a_p, 0.0 * a_p, 0.0 * a_p]))


class PlanarAbsolute(Convention):
    """Seed 004 planar bodies: one kind (0), a rotary joint about z whose angle offsets phi."""

    name = "planar"
    row_names = PLANAR_ROW
    kinds = (0,)
    reads_parent = True

    def local_transform(self, row, kind, qv) -> Pose:
        return planar_link(row, qv)

    def n_inputs(self, kind) -> int:
        return 1

    def is_prismatic(self, kind) -> bool:
        return False

    def joint_row_index(self, kind) -> int | None:
        return _PHI


register(PlanarAbsolute())
