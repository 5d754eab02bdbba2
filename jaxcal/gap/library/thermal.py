"""Thermal expansion about an unknown centre: every length of the robot, its mount and the set-up scales with the
thermal driver tau (standardised temperature, else time), about a centre c that is rarely the robot base origin p0
(the mount, the table and the tracker stand expand too):

    p' = c + (1 + kappa tau) (p - c) = p0 + (1 + kappa tau) (p - p0) + tau v,   v = kappa (p0 - c)

kappa is the parameter "gap.thermal", v (m per unit tau) "gap.thermal.x/y/z"; linear in (kappa, v), so the
centre needs no start and the refit stays a least-squares problem. v = 0 is expansion about the base origin.
On a closed mechanism a uniform scaling is a similarity (the closure is unchanged), so the transform is exact.
"""

from __future__ import annotations

from jaxcal.gap.effect import Effect


class Thermal(Effect):
    name = "thermal"
    per_joint = False
    acts_on = frozenset({"tool"})
    terms = ("", "x", "y", "z")
    needs = "thermal"

    def tool_transform(self, theta, R, p, origin, c):
        return R, origin + (1.0 + theta[0] * c.thermal) * (p - origin) + c.thermal * theta[1:]
