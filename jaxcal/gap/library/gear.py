"""Gear (transmission) error of a revolute joint, first and second harmonic of the joint angle:
dq_j = s1 sin q_j + c1 cos q_j + s2 sin 2q_j + c2 cos 2q_j."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.gap.effect import Effect


class Gear(Effect):
    name = "gear"
    per_joint = True
    acts_on = frozenset({"joint"})
    terms = ("s1", "c1", "s2", "c2")

    def applies(self, joint, revolute):
        return revolute

    def input_basis(self, q, c):
        return jnp.stack([jnp.sin(q), jnp.cos(q), jnp.sin(2 * q), jnp.cos(2 * q)], axis=1)

