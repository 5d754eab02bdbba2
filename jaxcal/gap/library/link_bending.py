"""Link bending: the links distal to joint j bend under the gravity moment perpendicular to its axis,
dphi_j = b_j (M_j - (z_j . M_j) z_j). Open chains only (in a closed loop the load needs the internal forces)."""

from __future__ import annotations

from jaxcal.gap.effect import Effect, load_box


class LinkBending(Effect):
    name = "link_bending"
    per_joint = True
    acts_on = frozenset({"gravity"})
    closed_loop = False

    def tool_rotation(self, theta, loads, axes):
        along = (loads * axes).sum(axis=1)
        return theta[:, 0][:, None] * (loads - along[:, None] * axes)

    box_limit = staticmethod(load_box)

