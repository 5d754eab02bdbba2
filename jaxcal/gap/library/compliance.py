"""Joint compliance: a revolute joint twists under the gravity torque about its axis.

Open chains: dphi_j = c_j (z_j . M_j) z_j, with M_j the gravity moment about joint j (kg m).
Closed loops: dq_j = c_j tau_j, tau_j the gravity load on actuator j (`jaxcal.gap.closed.platform_load`).
"""

from __future__ import annotations

from jaxcal.gap.effect import Effect, load_box


class Compliance(Effect):
    name = "compliance"
    per_joint = True
    acts_on = frozenset({"gravity", "actuator_load"})

    def applies(self, joint, revolute):
        return revolute

    def tool_rotation(self, theta, loads, axes):
        along = (loads * axes).sum(axis=1)
        return (theta[:, 0] * along)[:, None] * axes

    def actuator_offset(self, theta, load):
        return theta[:, 0] * load

    box_limit = staticmethod(load_box)

