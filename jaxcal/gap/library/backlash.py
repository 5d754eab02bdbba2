"""Backlash: the joint lags by b_j against its direction of approach, dq_j = b_j * direction_j (direction +-1)."""

from __future__ import annotations

from jaxcal.gap.effect import Effect


class Backlash(Effect):
    name = "backlash"
    per_joint = True
    acts_on = frozenset({"joint"})
    needs = "direction"

    def input_basis(self, q, c):
        return c.direction[:, None]

