"""Rigid transforms as a small pytree: Pose(R, p) with R (..., 3, 3) and p (..., 3)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Pose(NamedTuple):
    """A frame: rotation R (..., 3, 3) and origin p (..., 3), both in the parent frame."""

    R: jnp.ndarray
    p: jnp.ndarray

    @staticmethod
    def identity() -> "Pose":
        return Pose(jnp.eye(3), jnp.zeros(3))

    def compose(self, other: "Pose") -> "Pose":
        """self ∘ other: other expressed in self's frame."""
        return Pose(self.R @ other.R, self.p + (self.R @ other.p[..., None])[..., 0])

    def inverse(self) -> "Pose":
        Rt = jnp.swapaxes(self.R, -1, -2)
        return Pose(Rt, -(Rt @ self.p[..., None])[..., 0])

    def apply(self, x):
        """Map a point x (..., 3) from this frame to the parent frame."""
        return self.p + (self.R @ x[..., None])[..., 0]

    def matrix(self):
        """Homogeneous 4x4 matrix (..., 4, 4)."""
        top = jnp.concatenate([self.R, self.p[..., None]], axis=-1)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), top.shape[:-2] + (1, 4))
        return jnp.concatenate([top, bottom], axis=-2)

    @staticmethod
    def from_matrix(T) -> "Pose":
        T = jnp.asarray(T)
        return Pose(T[..., :3, :3], T[..., :3, 3])


jax.export.register_namedtuple_serialization(Pose, serialized_name="jaxcal.kin.Pose")  # outputs of kept programs


def translation(x, y, z) -> Pose:
    return Pose(jnp.eye(3), jnp.stack([x, y, z]))
