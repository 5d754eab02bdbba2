"""Rotations: principal rotations, Pitch-Roll-Yaw angles, Euler parameters, log/exp maps.

Conventions follow the seeds:
- PRY (seed 000 §3.1.3, eq 3.12-3.17): R = Rx(theta_x) Ry(theta_y) Rz(theta_z), rotations about
  the moving axes (X-Y-Z Euler angles). Inverse: eq 3.20-3.21 beside the two naive inverses.
  Eq 3.18 (arccos) is wrong outside the first quadrant; eq 3.19 returns the equivalent angle set
  (theta_x - 180, 180 - theta_y, theta_z - 180) when theta_y is in the 2nd/3rd quadrant, which is
  exactly Table 3.1. Eq 3.20-3.21 always returns the unique set with |theta_y| <= 90 deg and,
  unlike asin(r13), stays exact near theta_y = 90 deg.
- Euler parameters (seed 004 App. A.1, eq A.15-A.19): unit quaternion (eta0, eta1, eta2, eta3),
  scalar first; the matrix -> parameters map uses the largest-diagonal branch, the stable form of
  the eigenvector method near a half turn.
- Small pose differences (seed 001 Appendix I, eq 21-25).

Every function takes and returns jnp arrays, works on a single rotation (batch with vmap) and is
differentiable everywhere it is used (safe branches at zero angle).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def rot_x(angle):
    """Principal rotation about x (seed 000 eq 3.12)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


def rot_y(angle):
    """Principal rotation about y (seed 000 eq 3.13)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


def rot_z(angle):
    """Principal rotation about z (seed 000 eq 3.14)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    o, z = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def principal_rotation(axis: int, angle: float) -> np.ndarray:
    """Rx, Ry or Rz (axis 0, 1, 2) of one angle as a numpy array, for constants built on the host: no XLA program
    compiled (`rot_x` and its kin compile one per operation when called from Python)."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def pry_to_matrix(pry):
    """R = Rx(pry[0]) Ry(pry[1]) Rz(pry[2])  (seed 000 eq 3.15, 3.17), multiplied out (eq 3.17)."""
    ca, sa, cb, sb, cc, sc = (f(a) for a in (pry[0], pry[1], pry[2]) for f in (jnp.cos, jnp.sin))
    return jnp.stack([jnp.stack([cb * cc, -cb * sc, sb]),
                      jnp.stack([sa * sb * cc + ca * sc, ca * cc - sa * sb * sc, -sa * cb]),
                      jnp.stack([sa * sc - ca * sb * cc, ca * sb * sc + sa * cc, ca * cb])])


def matrix_to_pry(R):
    """Quadrant-safe PRY inverse (seed 000 eq 3.20-3.21).

    theta_y = atan2(r13, sqrt(r23^2 + r33^2)) in [-pi/2, pi/2]; theta_x = atan2(-r23, r33);
    theta_z = atan2(-r12, r11). Unique for |theta_y| < pi/2; the returned angles reproduce R
    in every quadrant (the angles themselves may differ from the input by the equivalent set).
    """
    theta_y = jnp.arctan2(R[0, 2], jnp.sqrt(R[1, 2] ** 2 + R[2, 2] ** 2))
    theta_x = jnp.arctan2(-R[1, 2], R[2, 2])
    theta_z = jnp.arctan2(-R[0, 1], R[0, 0])
    return jnp.stack([theta_x, theta_y, theta_z])


def matrix_to_pry_acos(R):
    """Naive inverse (seed 000 eq 3.18): theta_y from arccos, valid only for 0 <= angles <= 90/180 deg."""
    theta_y = jnp.arccos(jnp.clip(jnp.sqrt(R[1, 2] ** 2 + R[2, 2] ** 2), -1.0, 1.0))
    theta_x = jnp.arccos(jnp.clip(R[2, 2] / jnp.cos(theta_y), -1.0, 1.0))
    theta_z = jnp.arccos(jnp.clip(R[0, 0] / jnp.cos(theta_y), -1.0, 1.0))
    return jnp.stack([theta_x, theta_y, theta_z])


def matrix_to_pry_atan2(R):
    """Bai-Teo inverse (seed 000 eq 3.19): theta_y = asin(r13); wrong when cos(theta_y) < 0."""
    theta_y = jnp.arcsin(jnp.clip(R[0, 2], -1.0, 1.0))
    theta_x = jnp.arctan2(-R[1, 2], R[2, 2])
    theta_z = jnp.arctan2(-R[0, 1], R[0, 0])
    return jnp.stack([theta_x, theta_y, theta_z])


def skew(v):
    """Skew-symmetric matrix [v]x with [v]x w = v x w."""
    z = jnp.zeros_like(v[0])
    return jnp.stack(
        [jnp.stack([z, -v[2], v[1]]), jnp.stack([v[2], z, -v[0]]), jnp.stack([-v[1], v[0], z])]
    )


def vect(M):
    """vect(M) = 1/2 (M32 - M23, M13 - M31, M21 - M12): the inverse of skew on its antisymmetric part."""
    return 0.5 * jnp.stack([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])


def exp_so3(w):
    """Rodrigues: rotation of angle |w| about w/|w|; smooth (Taylor branch) at w = 0."""
    theta2 = jnp.dot(w, w)
    small = theta2 < 1e-12
    t2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(t2)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / t2)
    K = skew(w)
    return jnp.eye(3) + a * K + b * (K @ K)


def log_so3(R):
    """Rotation vector u*alpha of R (seed 001 eq 23-24), valid up to a half turn.

    Near zero alpha/sin(alpha) ~ 1 + (1 - cos alpha)/3 is used on vect(R) (eq 25), which keeps
    the derivative finite at R = I (where arccos is not differentiable); near a half turn the
    axis comes from the largest column of R + I = 2 u u^T.
    """
    cos_a = jnp.clip((jnp.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    v = vect(R)  # = u sin(alpha)
    small = cos_a > 1.0 - 1e-8
    near_pi = cos_a < -1.0 + 1e-8
    cos_safe = jnp.where(small | near_pi, 0.0, cos_a)
    alpha_safe = jnp.arccos(cos_safe)
    factor = jnp.where(small, 1.0 + (1.0 - cos_a) / 3.0, alpha_safe / jnp.sin(alpha_safe))
    regular = factor * v
    B = R + jnp.eye(3)
    k = jnp.argmax(jnp.diag(B))
    col = B[:, k]
    u = col / jnp.linalg.norm(col)
    u = jnp.where(jnp.dot(u, v) < 0, -u, u)
    alpha_pi = jnp.pi - jnp.sqrt(jnp.maximum(2.0 * (1.0 + jnp.where(near_pi, cos_a, -0.5)), 0.0))
    return jnp.where(near_pi, alpha_pi * u, regular)


def quat_from_matrix(R):
    """Euler parameters (eta0, eta) of R (seed 004 eq A.15-A.19), sign chosen with eta0 >= 0.

    Uses the branch with the largest of (trace, R11, R22, R33) so the division is well
    conditioned, including near a half turn where eta0 -> 0 (where the eigenvector method of
    A.19 is needed in the seed).
    """
    t = jnp.trace(R)
    d = jnp.diag(R)
    cands = jnp.stack([t, d[0], d[1], d[2]])
    k = jnp.argmax(cands)

    def branch0():
        s = jnp.sqrt(jnp.maximum(1.0 + t, 1e-300)) * 2.0
        return jnp.stack([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])

    def branch1():
        s = jnp.sqrt(jnp.maximum(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-300)) * 2.0
        return jnp.stack([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])

    def branch2():
        s = jnp.sqrt(jnp.maximum(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-300)) * 2.0
        return jnp.stack([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])

    def branch3():
        s = jnp.sqrt(jnp.maximum(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-300)) * 2.0
        return jnp.stack([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])

    qs = jnp.stack([branch0(), branch1(), branch2(), branch3()])
    q = qs[k]
    return jnp.where(q[0] < 0, -q, q)


def quat_eigen(R):
    """Euler parameters as the dominant eigenvector of the symmetric 4x4 matrix of seed 004 A.19.

    Slower than quat_from_matrix but uses no branch; kept as the independent check.
    """
    K = jnp.array(
        [
            [R[0, 0] + R[1, 1] + R[2, 2], R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]],
            [R[2, 1] - R[1, 2], R[0, 0] - R[1, 1] - R[2, 2], R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]],
            [R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], R[1, 2] + R[2, 1]],
            [R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1]],
        ]
    ) / 3.0
    w, V = jnp.linalg.eigh(K)
    q = V[:, -1]
    return jnp.where(q[0] < 0, -q, q)


def matrix_from_quat(q):
    """Rotation matrix of the Euler parameters q = (eta0, eta1, eta2, eta3) (seed 004 eq A.14)."""
    q = q / jnp.linalg.norm(q)
    w, x, y, z = q
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_difference_cross(Ri, Rj):
    """delta_ij = 1/2 (s_j x s_i + n_j x n_i + a_j x a_i)  (seed 001 eq 22, first method)."""
    return 0.5 * (jnp.cross(Rj[:, 0], Ri[:, 0]) + jnp.cross(Rj[:, 1], Ri[:, 1]) + jnp.cross(Rj[:, 2], Ri[:, 2]))


def rotation_difference_log(Ri, Rj):
    """delta_ij = u alpha with A_d = R_i R_j^T = Rot(u, alpha)  (seed 001 eq 23-24, second method)."""
    return log_so3(Ri @ Rj.T)


def pose_difference(Ri, pi, Rj, pj, method: str = "log"):
    """Delta x = [p_i - p_j; delta_ij]  (seed 001 eq 21), orientation by 'log' (eq 23-24) or 'cross' (eq 22)."""
    d = rotation_difference_log(Ri, Rj) if method == "log" else rotation_difference_cross(Ri, Rj)
    return jnp.concatenate([pi - pj, d])
