"""Drift of the device frame with time t (standardised): dv = t (v_d + w x v) on a position reading v,
and a frame reading turned by exp(t w)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.gap.effect import Effect


class Drift(Effect):
    name = "drift"
    per_joint = False
    acts_on = frozenset({"reading"})
    terms = ("vx", "vy", "vz", "wx", "wy", "wz")
    needs = "time"

    def reading_offset(self, theta, v, c):
        return c.time * (theta[:3] + jnp.cross(theta[3:], v))

    def reading_rotation(self, theta, c):
        return c.time * theta[3:]

