"""Encoder gain error: dq_j = g_j * q_j."""

from __future__ import annotations

from jaxcal.gap.effect import Effect


class EncoderGain(Effect):
    name = "encoder_gain"
    per_joint = True
    acts_on = frozenset({"joint"})

    def input_basis(self, q, c):
        return q[:, None]

