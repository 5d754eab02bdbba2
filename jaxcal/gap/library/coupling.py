"""Coupling of neighbouring joint inputs (an off-diagonal term of the motor-to-joint matrix): dq_j = k_j * q_{j-1}."""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.gap.effect import Effect


class Coupling(Effect):
    name = "coupling"
    per_joint = True
    acts_on = frozenset({"joint"})

    def applies(self, joint, revolute):
        return joint > 0

    def input_basis(self, q, c):
        return jnp.concatenate([jnp.zeros(1, q.dtype), q[:-1]])[:, None]

