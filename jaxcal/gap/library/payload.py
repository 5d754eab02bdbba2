"""Joint compliance under a payload at the tool: a revolute joint twists under the torque of a point mass at
the tool point, the ordinary case of an industrial arm carrying a gripper or a part.

Open chains: dphi_j = c_j (z_j . P_j) z_j with P_j = (p - o_j) x g_hat (kg m per kg of payload; p the tool
point, (o_j, z_j) the joint axis, g_hat = -z of the robot base frame). c_j is the joint's compliance times the
payload mass (rad per m), so the mass need not be known. `compliance` is the same twist under the robot's own
masses (its bodies' loads); the two load shapes differ wherever the links' masses are not at the tool.
"""

from __future__ import annotations

from jaxcal.gap.effect import Effect, load_box


class Payload(Effect):
    name = "payload"
    per_joint = True
    acts_on = frozenset({"payload"})
    closed_loop = False  # the Delta's compliance already loads its platform (a point mass at the tool)

    def applies(self, joint, revolute):
        return revolute

    def tool_rotation(self, theta, loads, axes):
        along = (loads * axes).sum(axis=1)
        return (theta[:, 0] * along)[:, None] * axes

    box_limit = staticmethod(load_box)
