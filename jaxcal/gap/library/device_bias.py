"""Device bias: dv = b + rho v / |v|; a constant offset b (absorbed by the device frame) and a range
offset rho (a laser tracker's)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.gap.effect import Effect


class DeviceBias(Effect):
    name = "device_bias"
    per_joint = False
    acts_on = frozenset({"reading"})
    terms = ("x", "y", "z", "range")

    def reading_offset(self, theta, v, c):
        return theta[:3] + theta[3] * v / jnp.sqrt(jnp.sum(v**2) + 1e-12)

