"""PRY six-parameter modules (seed 000 §3.2, eq 3.43-3.48, Table 3.3).

row = (bx, by, bz, pitch, roll, yaw). The module rotation is R = Rs Rm with Rs = Rx Ry Rz of the
PRY angles and Rm the motion part of the joint kind; the body vector b = bs + bm is expressed after
the rotation, so the local transform is (Rs Rm, Rs Rm b) and p_{n+1} = b0 + sum_i R_0i b_i
(eq 3.43). Because b is rotated with the module, the joint turns about the parent's origin.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.convention import Convention, register
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import pry_to_matrix, rot_x, rot_y, rot_z

# Joint kinds of seed 000 Table 3.3 and how many joint inputs each consumes.
PRY_KINDS = {"revolute": 1, "prismatic": 1, "cylindrical": 2, "universal": 2, "spherical": 3, "fixed": 0}
PRY_ROW = ("bx", "by", "bz", "pitch", "roll", "yaw")
_BZ, _YAW = 2, 5


def pry_motion(kind: str, qv):
    """(Rm, bm) of seed 000 Table 3.3 for joint values qv (length PRY_KINDS[kind])."""
    zero3 = jnp.zeros(3, dtype=jnp.result_type(float))
    if kind == "revolute":
        return rot_z(qv[0]), zero3
    if kind == "prismatic":
        return jnp.eye(3), zero3.at[2].set(qv[0])
    if kind == "cylindrical":
        return rot_z(qv[0]), zero3.at[2].set(qv[1])
    if kind == "universal":
        return rot_z(qv[0]) @ rot_y(qv[1]), zero3
    if kind == "spherical":
        return rot_z(qv[0]) @ rot_y(qv[1]) @ rot_x(qv[2]), zero3
    if kind == "fixed":
        return jnp.eye(3), zero3
    raise ValueError(f"unknown PRY joint kind {kind!r}; expected one of {sorted(PRY_KINDS)}")


def pry_module(row, kind: str, qv) -> Pose:
    """Local transform (Rs Rm, Rs Rm (bs + bm)) of one six-parameter module (eq 3.45-3.48)."""
    Rm, bm = pry_motion(kind, qv)
    R = pry_to_matrix(row[3:6]) @ Rm
    return Pose(R, R @ (row[0:3] + bm))


def pry_twists(row, kind: str, frame: Pose) -> jnp.ndarray:
    """The parent-frame twists (omega, v) (6 + inputs, 6) of the inputs (bx, by, bz, pitch, roll, yaw, joint values)
    of frame = `pry_module(row, kind, qv)` for the one-axis kinds and "cylindrical" (`Convention.local_twists`), in
    closed form: every turn is about an axis through the parent's origin (v = 0): pitch about x, roll about
    Rx(pitch) y, yaw and a rotary variable about Rx(pitch) Ry(roll) z; b slides along the module's axes R e_i, and a
    sliding variable along R z."""
    pitch, roll = row[3], row[4]
    ca, sa, cb, sb = jnp.cos(pitch), jnp.sin(pitch), jnp.cos(roll), jnp.sin(roll)
    zero = jnp.zeros_like(ca)
    nothing = jnp.zeros(3, ca.dtype)
    turn = lambda w: jnp.concatenate([w, nothing])  # noqa: E731
    slide = lambda u: jnp.concatenate([nothing, u])  # noqa: E731
    spin = turn(jnp.stack([sb, -sa * cb, ca * cb]))  # about Rx(pitch) Ry(roll) z = Rs z
    R = frame.R
    rows = [slide(R[:, 0]), slide(R[:, 1]), slide(R[:, 2]), turn(jnp.stack([zero + 1.0, zero, zero])),
            turn(jnp.stack([zero, ca, sa])), spin]
    rows += {"revolute": [spin], "prismatic": [slide(R[:, 2])], "cylindrical": [spin, slide(R[:, 2])], "fixed": []}[kind]
    return jnp.stack(rows)


class PryModules(Convention):
    """Seed 000 modules: Rs Rz(q) = Rx Ry Rz(yaw + q), so a rotary variable offsets yaw; a sliding
    one adds to bz."""

    name = "pry"
    row_names = PRY_ROW
    kinds = tuple(PRY_KINDS)

    def local_transform(self, row, kind, qv) -> Pose:
        return pry_module(row, kind, qv)

    def local_twists(self, row, kind, qv, frame: Pose):
        if kind in ("universal", "spherical"):  # two or three turns in a row: by forward mode
            return super().local_twists(row, kind, qv, frame)
        return pry_twists(row, kind, frame)

    def n_inputs(self, kind) -> int:
        return PRY_KINDS[kind]

    def is_prismatic(self, kind) -> bool:
        return kind == "prismatic"

    def joint_row_index(self, kind) -> int | None:
        if kind == "fixed":
            return None
        return _BZ if kind == "prismatic" else _YAW

    def axis_through_parent_origin(self, kind) -> bool:
        return True

    def motion_split(self, row, kind):
        """A = (Rs, 0), B = Trans(b): (Rs Rm, Rs Rm (b + bm)) = Rs M(q) Trans(b) for one-input and fixed kinds."""
        if self.n_inputs(kind) > 1:
            raise NotImplementedError(f"a {kind} PRY module has {self.n_inputs(kind)} joint variables; URDF joints have one")
        A, B = np.eye(4), np.eye(4)
        A[:3, :3] = np.asarray(pry_to_matrix(jnp.asarray(row[3:6], float)))
        B[:3, 3] = np.asarray(row[0:3], float)
        return A, B


PRY = register(PryModules())
