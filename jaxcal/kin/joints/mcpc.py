"""MCPC, the modified complete and parametrically continuous model (seed 004 §2.2, eq 2.1-2.18, 2.45).

row = (a1, a2, a3, d1, d2, d3); T = Rx(a1) Ry(a2) Trans(d1, d2, 0) Rz(a3) Trans(0, 0, d3). The
kind is the joint type: 0 rotary (the joint setting adds to a3), 1 prismatic (adds to d3),
2 spherical and 3 auxiliary, both constant frames here (a spherical joint is closed by position).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.kin.convention import Convention, register
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import rot_x, rot_y, rot_z

MCPC_ROW = ("a1", "a2", "a3", "d1", "d2", "d3")
_A3, _D3 = 2, 5


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


class Mcpc(Convention):
    """Seed 004 frames; the joint moves along or about the body's own z axis."""

    name = "mcpc"
    row_names = MCPC_ROW
    kinds = (0, 1, 2, 3)

    def local_transform(self, row, kind, qv) -> Pose:
        return mcpc_frame(row, kind, qv)

    def n_inputs(self, kind) -> int:
        return 1 if kind in (0, 1) else 0

    def is_prismatic(self, kind) -> bool:
        return kind == 1

    def joint_row_index(self, kind) -> int | None:
        return {0: _A3, 1: _D3}.get(kind)


register(Mcpc())
