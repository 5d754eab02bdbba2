"""Joint compliance under a payload at the tool: a revolute joint twists under the torque of a point mass at
the tool point, the ordinary case of an industrial arm carrying a gripper or a part.

Open chains: dphi_j = c_j (z_j . P_j) z_j with P_j = (p - o_j) x g_hat (kg m per kg of payload; p the tool
point, (o_j, z_j) the joint axis, g_hat = -z of the robot base frame; `jaxcal.gap.effects.payload_loads`).
c_j is the joint's compliance times the payload mass (rad per m), so the mass need not be known. The twist is
`compliance`'s; only the load differs (the robot's own masses there), and the two load shapes differ wherever
the links' masses are not at the tool.
"""

from __future__ import annotations

from jaxcal.gap.library.compliance import Compliance


class Payload(Compliance):
    name = "payload"
    acts_on = frozenset({"payload"})
    closed_loop = False  # the Delta's compliance already loads its platform (a point mass at the tool)
