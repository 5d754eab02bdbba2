"""Clavel's original direct solution of the Delta robot and its numerical breakdown (seed 004 §2.6,
"Geometric Solution of R. Clavel", eq 2.118-2.134).

Notation of `jaxcal.closure.delta` (Figure 2.6): base radius rb, nacelle radius rn, arm n, rods m,
arm azimuths psi_i, actuated angle theta_i below the horizontal, elbow B_i of eq 2.114. The nacelle
stays parallel to the base, so its rod end C_i = P + rn (cos psi_i, sin psi_i, 0) (eq 2.117) and
each rod gives a sphere |C_i - B_i| = m (eq 2.116). The thesis eliminates |P|^2 between the three
spheres: the two remaining linear equations give p1 and p2 as linear functions of p3 (eq 2.120-2.121),
and the first sphere then gives a quadratic in p3 (eq 2.122). Every coefficient is divided by the
determinant h2 (eq 2.124), which vanishes when the three sphere centres lie in a vertical plane; with
the design ratio K = (rb - rn) / n (eq 2.132) h2 is quadratic in K (eq 2.133) and its roots K_crit
(eq 2.134) mark where the closed form breaks down.

The OCR of the seed keeps eq 2.123 (h1), 2.124 (h2), 2.125 (h3, partly), the pattern of h5 and the
forms of D_i and L; the bodies of eq 2.118-2.119, 2.126 (h4) and 2.128-2.131 (M, N) are lost and are
derived here from eq 2.116-2.117 by Cramer's rule (the tests hold them to the general closure).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.closure.delta import NOMINAL, DeltaGeometry, elbows


def _pattern(x, y):
    """x1 y3 - x1 y2 + x2 y1 - x2 y3 + x3 y2 - x3 y1: the 3 x 3 determinant pattern of eq 2.123-2.126."""
    return x[0] * (y[2] - y[1]) + x[1] * (y[0] - y[2]) + x[2] * (y[1] - y[0])


def sphere_coefficients(theta, g: DeltaGeometry = NOMINAL):
    """(e, f, gz, D) (3,) each, of the spheres (p1 + e_i)^2 + (p2 + f_i)^2 + (p3 + gz_i)^2 = m^2
    (eq 2.118-2.119: e_i = rn cos psi_i - b1i, f_i = rn sin psi_i - b2i, gz_i = -b3i) and
    D_i = (m^2 - e_i^2 - f_i^2 - gz_i^2) / 2 (eq 2.127), so that |P|^2 + 2 (e_i p1 + f_i p2 + gz_i p3) = 2 D_i."""
    b = elbows(jnp.asarray(theta, dtype=jnp.float64), g)
    psi = jnp.asarray(g.psi)
    e = g.rn * jnp.cos(psi) - b[:, 0]
    f = g.rn * jnp.sin(psi) - b[:, 1]
    gz = -b[:, 2]
    return e, f, gz, (g.m**2 - e**2 - f**2 - gz**2) / 2.0


def h_terms(e, f, gz, D):
    """(h1, h2, h3, h4, h5) of eq 2.123-2.126: h1 = -pattern(e, g), h2 = pattern(e, f),
    h3 = pattern(e, D), h4 = pattern(f, D), h5 = pattern(f, g)."""
    return -_pattern(e, gz), _pattern(e, f), _pattern(e, D), _pattern(f, D), _pattern(f, gz)


def direct(theta, g: DeltaGeometry = NOMINAL):
    """Nacelle centre P (3,) for actuator angles theta (3,) by Clavel's solution, and a flag (real
    root and h2 != 0). p1 = (p3 h5 - h4) / h2, p2 = (p3 h1 + h3) / h2 (eq 2.120-2.121, Cramer's rule on
    the differences of the spheres); substituted into sphere 1: L p3^2 + M p3 + N = 0 with
    L = (h1^2 + h5^2) / h2^2 + 1 (eq 2.128-2.131), p3 = (-M - sqrt(M^2 - 4 L N)) / 2L, the lower
    root (eq 2.122)."""
    e, f, gz, D = sphere_coefficients(theta, g)
    h1, h2, h3, h4, h5 = h_terms(e, f, gz, D)
    a1, c1 = h5 / h2, -h4 / h2 + e[0]  # p1 + e_1 = a1 p3 + c1
    a2, c2 = h1 / h2, h3 / h2 + f[0]  # p2 + f_1 = a2 p3 + c2
    L = a1**2 + a2**2 + 1.0
    M = 2.0 * (a1 * c1 + a2 * c2 + gz[0])
    N = c1**2 + c2**2 + gz[0] ** 2 - g.m**2
    disc = M**2 - 4.0 * L * N
    ok = (disc >= 0.0) & (h2 != 0.0)
    p3 = (-M - jnp.sqrt(jnp.where(ok, disc, 0.0))) / (2.0 * L)
    return jnp.stack([(p3 * h5 - h4) / h2, (p3 * h1 + h3) / h2, p3]), ok


def design_ratio(g: DeltaGeometry = NOMINAL) -> float:
    """K = (rb - rn) / n (eq 2.132): with e_i = -n (K + cos theta_i) cos psi_i and
    f_i = -n (K + cos theta_i) sin psi_i, h2 depends on the geometry through K alone."""
    return (g.rb - g.rn) / g.n


def h2_of_ratio(theta, K, psi=NOMINAL.psi):
    """h2 / n^2 as a function of K (eq 2.133): sum_i sin psi_i u_i (u_{i+1} cos psi_{i+1} -
    u_{i-1} cos psi_{i-1}) with u_i = K + cos theta_i, indices cyclic."""
    u = K + jnp.cos(jnp.asarray(theta))
    psi = jnp.asarray(psi)
    uc = u * jnp.cos(psi)
    return jnp.sum(jnp.sin(psi) * u * (jnp.roll(uc, -1) - jnp.roll(uc, 1)))


def ratio_quadratic(theta, psi=NOMINAL.psi):
    """(A, B, C) with h2 / n^2 = A K^2 + B K + C (eq 2.133): with S_ij = sin(psi_i - psi_j) over the
    pairs (1, 2), (2, 3), (3, 1) and c = cos theta, A = sum S_ij, B = sum S_ij (c_i + c_j),
    C = sum S_ij c_i c_j."""
    c = jnp.cos(jnp.asarray(theta))
    psi = jnp.asarray(psi)
    s = jnp.sin(psi - jnp.roll(psi, -1))
    cn = jnp.roll(c, -1)
    return jnp.sum(s), jnp.sum(s * (c + cn)), jnp.sum(s * c * cn)


def k_crit(theta, psi=NOMINAL.psi):
    """The two design ratios (lower, upper) at which h2 = 0 for actuator angles theta (eq 2.134).
    For arms 120 degrees apart this is (-q1 -+ sqrt(q1^2 - 3 q2)) / 3 with q1 = sum cos theta_i and
    q2 = sum_{i<j} cos theta_i cos theta_j; the discriminant is then sum (c_i - c_j)^2 / 2 >= 0, so
    both roots are real everywhere."""
    A, B, C = ratio_quadratic(theta, psi)
    root = jnp.sqrt(jnp.maximum(B**2 - 4.0 * A * C, 0.0))
    lo, hi = (-B - root) / (2.0 * A), (-B + root) / (2.0 * A)
    return jnp.minimum(lo, hi), jnp.maximum(lo, hi)


def actuator_box(lo, hi, n=41):
    """All (n^3, 3) actuator settings of a grid over [lo, hi]^3, bounds included."""
    ax = np.linspace(lo, hi, n)
    return np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)


def k_crit_max_bound(lo, hi) -> float:
    """K_crit,1 over the actuator box [lo, hi]^3 (-pi <= lo < hi <= pi) for arms 120 degrees apart:
    -min cos theta = -cos max(|lo|, |hi|). h2 / n^2 = (sqrt 3 / 2) (u1 u2 + u2 u3 + u3 u1) cannot
    vanish while every u_i = K + cos theta_i > 0, so K_crit <= -cos theta_i for some i; two arms at
    the smallest cosine reach it (u1 = u2 = 0)."""
    return float(-np.cos(max(abs(lo), abs(hi))))
