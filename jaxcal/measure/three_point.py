"""Three-point device ("three_point"): a known target of three sphere centres rigid on the tip
link, read together in the device frame, y = [D^-1 T_tip t_1, D^-1 T_tip t_2, D^-1 T_tip t_3]
(3, 3); the target's orientation follows from the three points (seed 000 §3.3,
`three_point_orientation`). Parameters: the device frame D (6); the centres t_k are known."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from jaxcal.measure.base import FRAME_INDEX, frame_from_params, frame_names
from jaxcal.measure.multi_position import PointSetDevice
from jaxcal.measure.registry import register

DEFAULT_TARGETS = ((0.05, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 0.05))  # m, in the tip frame


@dataclasses.dataclass(frozen=True, eq=False)
class ThreePoint(PointSetDevice):
    """A known three-sphere target read in the device frame."""

    targets: np.ndarray = None  # sphere centres in the tip frame (3, 3)

    kind = "three_point"
    residual_components = ("length",) * 9
    frame_index = FRAME_INDEX

    @classmethod
    def build(cls, targets=None) -> "ThreePoint":
        targets = np.array(DEFAULT_TARGETS) if targets is None else np.asarray(targets, float)
        if targets.shape != (3, 3):
            raise ValueError(f"three_point targets must be 3 sphere centres (3, 3), got shape {targets.shape}")
        return cls.nominal_device(frame_names("dev"), (3, 3), targets=targets)

    @property
    def n_points(self) -> int:
        return 3

    def read(self, tip, d):
        """y_k = D^-1 T_tip t_k for the three known centres t_k."""
        return frame_from_params(d[0:6]).inverse().apply(tip.apply(jnp.asarray(self.targets)))



def three_point_orientation(P_initial, P_final):
    """Rotation taking a three-point target from its initial to its final pose (seed 000 §3.3).

    With the line vectors v1 = p2 - p1, v2 = p3 - p1 and v3 = v1 x v2 of each triad as columns,
    R = [v'1 v'2 v'3][v1 v2 v3]^-1; with noisy points that product is not orthogonal, so it is
    replaced by the nearest rotation in the Frobenius norm, U diag(1, 1, det(U V^T)) V^T from its SVD.
    """

    def lines(P):
        v1, v2 = P[1] - P[0], P[2] - P[0]
        return jnp.stack([v1, v2, jnp.cross(v1, v2)], axis=1)

    A = lines(P_final) @ jnp.linalg.inv(lines(P_initial))
    U, _, Vt = jnp.linalg.svd(A)
    S = jnp.diag(jnp.array([1.0, 1.0, jnp.linalg.det(U @ Vt)]))
    return U @ S @ Vt


register(ThreePoint)
