"""Khalil-Kleinfinger modified DH with Hayati's beta (seed 001 eq 2-3).

row = (alpha, d, theta, r, beta); T = Rot(y, beta) Rot(x, alpha) Trans(x, d) Rot(z, theta) Trans(z, r).
The kind is sigma: 0 rotary (the joint variable adds to theta), 1 prismatic (adds to r), 2 a
constant frame.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcal.kin.convention import Convention, register
from jaxcal.kin.pose import Pose

MDH_ROW = ("alpha", "d", "theta", "r", "beta")
_THETA, _R = 2, 3


def mdh_frame(row, sigma: int, qv) -> Pose:
    """Khalil-Kleinfinger frame with Hayati beta (seed 001 eq 3); qv = (joint variable,) or (). R = Ry(beta) Rx(alpha)
    Rz(theta) and p = Ry(beta) (d, 0, 0) + Ry(beta) Rx(alpha) (0, 0, r) are multiplied out: no 3 x 3 products, which
    XLA:CPU runs as one kernel each (docs/benchmarks.md, 2026-11-29)."""
    alpha, d, theta, r, beta = row
    if sigma == 0:
        theta = theta + qv[0]
    elif sigma == 1:
        r = r + qv[0]
    ca, sa, ct, st, cb, sb = jnp.cos(alpha), jnp.sin(alpha), jnp.cos(theta), jnp.sin(theta), jnp.cos(beta), jnp.sin(beta)
    R = jnp.stack([jnp.stack([cb * ct + sb * sa * st, sb * sa * ct - cb * st, sb * ca]),
                   jnp.stack([ca * st, ca * ct, -sa]),
                   jnp.stack([cb * sa * st - sb * ct, sb * st + cb * sa * ct, cb * ca])])
    p = jnp.stack([cb * d + sb * ca * r, -sa * r, cb * ca * r - sb * d])
    return Pose(R, p)


def mdh_twists(row, sigma: int, frame: Pose) -> jnp.ndarray:
    """The parent-frame twists (omega, v) (k, 6) of the inputs (alpha, d, theta, r, beta, then the joint variable) of
    frame = `mdh_frame(row, sigma, qv)` (seed 001 eq 3; `Convention.local_twists`), in closed form: beta turns about
    the parent's y, alpha about x1 = Ry(beta) x, d slides along x1, theta turns about z' = R z through o' = d x1
    (v = o' x z'), r slides along z'."""
    d, beta = row[1], row[4]
    cb, sb = jnp.cos(beta), jnp.sin(beta)
    zero = jnp.zeros_like(cb)
    x1 = jnp.stack([cb, zero, -sb])
    z = frame.R[:, 2]
    o = d * x1
    turn_z = jnp.concatenate([z, jnp.cross(o, z)])
    slide_z = jnp.concatenate([jnp.zeros(3, z.dtype), z])
    rows = [jnp.concatenate([x1, jnp.zeros(3, z.dtype)]), jnp.concatenate([jnp.zeros(3, z.dtype), x1]), turn_z, slide_z,
            jnp.stack([zero, zero + 1.0, zero, zero, zero, zero])]
    if sigma in (0, 1):
        rows.append(turn_z if sigma == 0 else slide_z)
    return jnp.stack(rows)


class ModifiedDH(Convention):
    """Seed 001 frames; the joint moves along or about the body's own z axis."""

    name = "mdh"
    row_names = MDH_ROW
    kinds = (0, 1, 2)

    def local_transform(self, row, kind, qv) -> Pose:
        return mdh_frame(row, kind, qv)

    def local_twists(self, row, kind, qv, frame: Pose):
        return mdh_twists(row, kind, frame)

    def n_inputs(self, kind) -> int:
        return 1 if kind in (0, 1) else 0

    def is_prismatic(self, kind) -> bool:
        return kind == 1

    def joint_row_index(self, kind) -> int | None:
        return {0: _THETA, 1: _R}.get(kind)


register(ModifiedDH())
