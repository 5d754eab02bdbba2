"""Thermal expansion: every length of the robot scales with the thermal driver tau (standardised
temperature, else time), so the tool point scales about the base origin p0: p' = p0 + (1 + kappa tau) (p - p0).
On a closed mechanism a uniform scaling is a similarity (the closure is unchanged), so the same transform is exact."""

from __future__ import annotations

from jaxcal.gap.effect import Effect


class Thermal(Effect):
    name = "thermal"
    per_joint = False
    acts_on = frozenset({"tool"})
    needs = "thermal"

    def tool_transform(self, theta, R, p, origin, c):
        return R, origin + (1.0 + theta[0] * c.thermal) * (p - origin)

