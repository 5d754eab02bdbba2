"""GA fitness functions (seed 000 eq 5.2-5.6).

`pose_fitness`: sum over measurements of w1 ||P_m - P_0||_2 + w2 ||R_m - R_0||_2, with the
spectral norm of the rotation difference. For two rotations, R_m - R_0 = R_0 (R_0^T R_m - I) and
R_0^T R_m - I is normal with eigenvalues 0, e^{+-i theta} - 1, so ||R_m - R_0||_2 = 2 sin(theta/2)
= sqrt(3 - tr(R_0^T R_m)) exactly (checked against the SVD in the tests). Evaluated as 3 - tr(R_0^T R_m) =
|R_m - R_0|_F^2 / 2 (both have |R|_F^2 = 3): the trace form subtracts two numbers near 3, which at the GA's
fitness limit (seed 000 §6.2: 1e-5, rotation errors of ~5 urad, 3 - tr ~ 2.5e-11) leaves ~1e-5 relative error;
the differences keep ~1e-10.
`residual_fitness`: sum of squares of any jc weighted residual (jaxcal.fit.identify.residuals),
so the GA works with every device and robot jc models.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcal.fit.identify import residuals
from jaxcal.forward import forward


def rotation_spectral_distance(Ra, Rb):
    """||Ra - Rb||_2 for rotation matrices: sqrt(3 - tr(Rb^T Ra)) (= 2 sin(theta/2)), as sqrt(|Ra - Rb|_F^2 / 2)."""
    return jnp.sqrt(0.5 * jnp.sum((Ra - Rb) ** 2, axis=(-2, -1)))


def full_vector(dg, a0, free_idx):
    """a = g + dg on the free entries (seed eq 5.5-5.6); a0 is the full robot+device vector."""
    return a0.at[free_idx].add(dg)


def pose_fitness(robot, device, a_full, q, y, w1=1.0, w2=1.0):
    """Seed eq 5.3-5.4 for readings y of one marker point (e.g. "position") or one marker frame (e.g. "pose")."""
    nr = robot.n_params
    tips = forward(robot, a_full[:nr], q)
    pred = jax.vmap(device.read, (0, None))(tips, a_full[nr:])
    if device.marker_reading == "point":
        return w1 * jnp.sum(jnp.linalg.norm(pred - y, axis=-1))
    if device.marker_reading != "frame":
        raise ValueError(f"pose fitness needs a 'position' or 'pose' device, got {device.kind!r}; use fitness='residual'")
    dp = jnp.linalg.norm(pred[:, :3, 3] - y[:, :3, 3], axis=-1)
    dR = rotation_spectral_distance(y[:, :3, :3], pred[:, :3, :3])
    return jnp.sum(w1 * dp + w2 * dR)


def residual_fitness(robot, device, a_full, q, y, w):
    """Sum of squared weighted jc residuals (any device)."""
    return jnp.sum(residuals(robot, device, a_full, q, y, w) ** 2)
