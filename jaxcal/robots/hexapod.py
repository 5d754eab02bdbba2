"""Gough-Stewart platforms (hexapods): six legs, each a base universal joint, a prismatic actuator and a
platform spherical joint, built as one MCPC tree with spherical closures (seed 004 Table 4.1 layout).

Bodies (numbered as in the table, predecessor in brackets):

- 1-6 a floating chain that carries the platform: slides along the base z, y, x axes, then turns about z, y, x
  through the base origin (all free joints, 0 at home). It has no physical counterpart: its parameters have no
  effect on the closed pose (the free joints absorb them) and are fixed with priority 0.
- 7 the platform frame (auxiliary, [6]): the home pose at zero floating joints; 8 the tool frame when a tool
  offset is given (auxiliary, [7]).
- per leg i, five bodies: `legi_base` (auxiliary, [0]) at the base point a_i, row (0, 0, 0, a_i): d1 d2 d3 are
  its base-frame coordinates; `legi_u1`, `legi_u2` the universal joint (free rotary joints through a_i, the
  first axis perpendicular to the leg at home, the second perpendicular to both); `legi_slide` the actuator
  (prismatic along the leg): its origin is a_i + (q_i + d3) n_i, so q_i is the leg length (m) and d3 its offset
  (0 nominal); `legi_ball` (spherical, [7]) at the platform point b_i, row (0, 0, 0, b_i) in the platform
  frame, closing (position) with `legi_slide`.

18 free joints (6 floating + 2 per leg) against 6 x 3 closure equations. The closure starts at the home
pose (every free joint 0 there) and follows the nominal branch by continuation (`jaxcal.closure.track`):
the forward kinematics of a hexapod has no closed form and up to 40 assembly modes; a sample either
closes on the branch connected to home or is flagged.

Identifiable geometry (docs/hexapod.md): the 42 numbers a_i, b_i and the leg offsets. A full-pose device
whose frame and marker offset are identified with the robot absorbs a rigid motion of the base points
(the device frame) and one of the platform points (the marker offset): 12 directions, so 30 are
identifiable; the default free set fixes the 6 base and 6 platform coordinates that pivoted QR of the
rigid-motion generators picks (`rigid_coordinates`).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from jaxcal.kin.model import Robot
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import principal_rotation, rot_x, rot_y
from jaxcal.robots.build import MCPC_USED, mcpc_robot

N_LEGS = 6
ROTARY, PRISMATIC, SPHERICAL, AUXILIARY = 0, 1, 2, 3
LEG_BODIES = ("base", "u1", "u2", "slide", "ball")
FLOATING = ("float_z", "float_y", "float_x", "float_rz", "float_ry", "float_rx")
# floating chain at zero joints: (type, world rotation of its frame); every frame at the base origin. The prismatic
# frames are the ones MCPC allows (a3 = 0): Rx(a1) Ry(a2) of the previous one.
_FLOATING_FRAMES = (
    (PRISMATIC, np.eye(3)),                                                       # slides along z
    (PRISMATIC, principal_rotation(0, -np.pi / 2)),                               # along y
    (PRISMATIC, principal_rotation(0, -np.pi / 2) @ principal_rotation(1, np.pi / 2)),  # along x
    (ROTARY, np.eye(3)),                                                          # turns about z
    (ROTARY, principal_rotation(0, -np.pi / 2)),                                  # about y
    (ROTARY, principal_rotation(0, -np.pi / 2) @ principal_rotation(1, np.pi / 2)),     # about x
)
SINGULAR_RCOND = 1e-6  # smallest / largest singular value of the home leg Jacobian below which the layout is singular
STROKE_FRACTION = 0.2  # default leg limits: home length -/+ this fraction
ROTATION_TOL = 1e-9
ROUND_OFF = 1e-14  # row entries below this (m or rad) are round-off of the frame construction: written as 0


def leg_lengths(base_points, platform_points, R, p):
    """Inverse kinematics: l_i = |p + R b_i - a_i| for platform pose (R, p) (..., 3, 3)/(..., 3), platform
    points b_i (6, 3) in the platform frame and base points a_i (6, 3) in the base frame; (..., 6). Pure jnp
    (jit, vmap, jacfwd)."""
    ends = jnp.einsum("...jk,ik->...ij", jnp.asarray(R, float), jnp.asarray(platform_points, float))
    return jnp.linalg.norm(ends + jnp.asarray(p, float)[..., None, :] - jnp.asarray(base_points, float), axis=-1)


def _mcpc_row(parent: Pose, child: Pose, typ: int) -> list[float]:
    """MCPC row (a1 a2 a3 d1 d2 d3) with T(row) = parent^-1 child at joint value 0: Rx(a1) Ry(a2) Rz(a3) is the
    relative rotation, (d1, d2, d3) = (Rx(a1) Ry(a2))^T of the relative origin; entries the type leaves unused
    (seed 004 eq 2.45) and round-off (|x| < ROUND_OFF) are set to 0."""
    R = parent.R.T @ child.R
    a = _xyz_angles(R)
    d = np.asarray(rot_x(a[0]) @ rot_y(a[1]), float).T @ (parent.R.T @ (child.p - parent.p))
    row = np.concatenate([a, d])
    row[np.abs(row) < ROUND_OFF] = 0.0
    used = MCPC_USED[typ]
    return [float(v) if f in used else 0.0 for f, v in zip(("a1", "a2", "a3", "d1", "d2", "d3"), row)]


def _xyz_angles(R) -> np.ndarray:
    """(a1, a2, a3) with R = Rx(a1) Ry(a2) Rz(a3), |a2| <= pi/2; at a2 = +-pi/2 (only a1 + a3 or a1 - a3 is
    defined) a1 = 0."""
    c2 = np.hypot(R[1, 2], R[2, 2])
    a2 = np.arctan2(R[0, 2], c2)
    if c2 < 1e-12:
        return np.array([0.0, a2, np.arctan2(R[1, 0], R[1, 1])])
    return np.array([np.arctan2(-R[1, 2], R[2, 2]), a2, np.arctan2(-R[0, 1], R[0, 0])])


def _unit(v):
    return v / np.linalg.norm(v)


def _leg_frames(a_i, c_i):
    """Home frames (base, u1, u2, slide at q = 0) of a leg from base point a_i to ball centre c_i: with n the leg
    direction, u1 = n x e (e = x, or y when n is within 45 degrees of x: the axis stays off the base x axis, where
    the MCPC angles a1, a2 are singular) and u2 = n x u1, the frames are
    [-n, u2, u1], [-u1, n, u2] and [-u1, -u2, n] = [-u1, n, u2] Rx(-pi/2) (the prismatic frame MCPC allows)."""
    n = _unit(c_i - a_i)
    u1 = _unit(np.cross(n, np.eye(3)[0 if abs(n[0]) < np.sqrt(0.5) else 1]))
    u2 = np.cross(n, u1)
    return (Pose(np.eye(3), a_i), Pose(np.column_stack([-n, u2, u1]), a_i),
            Pose(np.column_stack([-u1, n, u2]), a_i), Pose(np.column_stack([-u1, -u2, n]), a_i))


def rigid_coordinates(points) -> np.ndarray:
    """The 6 coordinates (flat indices 3 i + k into points (6, 3)) that a rigid motion dx_i = v + w x x_i moves
    most independently: the first 6 pivots of QR with column pivoting of G^T, G (18, 6) = [I, -[x_i]x]. Fixing
    them removes the 6 rigid-motion directions from the points."""
    x = np.asarray(points, float)
    G = np.concatenate([np.tile(np.eye(3), (len(x), 1)), -np.concatenate([_skew(xi) for xi in x])], axis=1)
    _, _, piv = scipy.linalg.qr(G.T, pivoting=True)
    return np.sort(piv[:6])


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _as_pose(pose, what: str) -> Pose:
    """A Pose from a Pose, an (R, p) pair or a 4x4 matrix; R must be a rotation."""
    if isinstance(pose, Pose) or (isinstance(pose, (tuple, list)) and len(pose) == 2):
        R, p = (np.asarray(v, float) for v in pose)
    else:
        T = np.asarray(pose, float)
        if T.shape != (4, 4):
            raise ValueError(f"{what} must be a Pose, an (R, p) pair or a 4x4 matrix, got shape {T.shape}")
        R, p = T[:3, :3], T[:3, 3]
    if R.shape != (3, 3) or p.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
        raise ValueError(f"{what}: expected a finite rotation (3, 3) and position (3,), got {R.shape} and {p.shape}")
    if np.max(np.abs(R.T @ R - np.eye(3))) > ROTATION_TOL or np.linalg.det(R) < 0:
        raise ValueError(f"{what}: R is not a rotation matrix (R^T R = I, det R = +1)")
    return Pose(R, p)


def _points(x, what: str) -> np.ndarray:
    """(6, 3) finite points, not all on one line."""
    x = np.asarray(x, float)
    if x.shape != (N_LEGS, 3) or not np.all(np.isfinite(x)):
        raise ValueError(f"{what} must be {N_LEGS} finite points, shape ({N_LEGS}, 3), got shape {x.shape}")
    s = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError(f"{what} are collinear (or coincide): a hexapod needs them spread in a plane or in space")
    return x


def _stroke(stroke, home_lengths) -> tuple[np.ndarray, np.ndarray]:
    """(q_min, q_max) from stroke (min, max) leg lengths (numbers or 6 each; default home -/+ STROKE_FRACTION)."""
    if stroke is None:
        return (1.0 - STROKE_FRACTION) * home_lengths, (1.0 + STROKE_FRACTION) * home_lengths
    if np.isscalar(stroke) or len(stroke) != 2:
        raise ValueError(f"stroke must be (shortest, longest) leg length, got {stroke!r}")
    try:
        lo, hi = (np.broadcast_to(np.asarray(v, float), (N_LEGS,)).copy() for v in stroke)
    except ValueError:
        raise ValueError(f"stroke: shortest and longest must be numbers or {N_LEGS} each, got {stroke!r}") from None
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo > 0) and np.all(lo < hi)):
        raise ValueError(f"stroke must be finite leg lengths 0 < shortest < longest, got {stroke!r}")
    out = np.flatnonzero((home_lengths < lo) | (home_lengths > hi))
    if out.size:
        legs = ", ".join(f"leg {i + 1}: {home_lengths[i]:.6g} m not in [{lo[i]:.6g}, {hi[i]:.6g}]" for i in out)
        raise ValueError(f"the leg limits exclude the home pose ({legs})")
    return lo, hi


def _check_home(a, b, home: Pose) -> np.ndarray:
    """Home leg lengths; raises when a leg has zero length or the legs are singular at home: the rows
    [n_i, (R b_i) x n_i] of the leg-length Jacobian d l / d (p, w) must span R^6."""
    ends = home.p + b @ home.R.T
    legs = ends - a
    lengths = np.linalg.norm(legs, axis=1)
    zero = lengths <= 1e-9 * max(np.max(lengths), 1e-300)
    if np.any(zero):
        raise ValueError(f"legs {(np.flatnonzero(zero) + 1).tolist()} have zero length at the home pose")
    n = legs / lengths[:, None]
    s = np.linalg.svd(np.concatenate([n, np.cross(ends - home.p, n)], axis=1), compute_uv=False)
    if s[-1] <= SINGULAR_RCOND * s[0]:
        raise ValueError(f"the legs are in a singular configuration at the home pose (leg Jacobian singular values "
                         f"{s[0]:.3g} .. {s[-1]:.3g}): choose another layout or home pose")
    return lengths


def hexapod_robot(base_points, platform_points, *, home_pose, stroke=None, tool=None, name: str = "hexapod") -> Robot:
    """A Gough-Stewart platform as a closed MCPC robot (module docstring).

    base_points (6, 3): universal-joint centres a_i in the base frame (m); platform_points (6, 3): spherical-joint
    centres b_i in the platform frame (m); leg i joins a_i and b_i. home_pose: the platform pose the closure starts
    from (a Pose, an (R, p) pair or a 4x4 matrix), also `robot.home` (its leg lengths). stroke: (shortest,
    longest) leg length, numbers or six each (default home length -/+ 20 %); it must contain the home lengths.
    tool: optional tool offset (same forms) in the platform frame: the tool frame is the platform frame otherwise.

    Inputs: the six leg lengths (m), joint names leg1..leg6. Free parameters (30): the base points
    `legi_base.d1..d3`, platform points `legi_ball.d1..d3` and leg offsets `legi_slide.d3`, less the 6 + 6
    coordinates of `rigid_coordinates` that a full-pose device's frame and marker offset absorb.
    """
    a = _points(base_points, "base_points")
    b = _points(platform_points, "platform_points")
    home = _as_pose(home_pose, "home_pose")
    lengths = _check_home(a, b, home)
    q_min, q_max = _stroke(stroke, lengths)
    world = [Pose(R, np.zeros(3)) for _, R in _FLOATING_FRAMES]
    rows = []
    for k, (typ, _) in enumerate(_FLOATING_FRAMES):
        rows.append(_mcpc_row(world[k - 1] if k else Pose(np.eye(3), np.zeros(3)), world[k], typ) + [k, 0, typ])
    rows.append(_mcpc_row(world[-1], home, AUXILIARY) + [6, 0, AUXILIARY])
    platform = len(rows)
    if tool is not None:
        rows.append(_mcpc_row(Pose(np.eye(3), np.zeros(3)), _as_pose(tool, "tool"), AUXILIARY) + [platform, 0, AUXILIARY])
    tip = len(rows)  # the platform, or the tool, body; the legs follow, five bodies each
    for i in range(N_LEGS):
        c_i = home.p + home.R @ b[i]
        frames = _leg_frames(a[i], c_i)
        first = len(rows) + 1
        parents = (Pose(np.eye(3), np.zeros(3)),) + frames[:-1]
        for k, (typ, frame, parent) in enumerate(zip((AUXILIARY, ROTARY, ROTARY, PRISMATIC), frames, parents)):
            rows.append(_mcpc_row(parent, frame, typ) + [first + k - 1 if k else 0, 0, typ])
        rows.append([0.0, 0.0, 0.0, *b[i]] + [platform, first + 3, SPHERICAL])
    slides = [tip + 5 * i + 4 for i in range(N_LEGS)]
    robot = mcpc_robot(name, rows, actuated=slides, home=lengths, q_min=q_min, q_max=q_max,
                       joint_names=[f"leg{i + 1}" for i in range(N_LEGS)], tip=tip)
    return _named(robot, a, b, tool is not None)


def _named(robot: Robot, a, b, has_tool: bool) -> Robot:
    """The MCPC robot with readable body and parameter names, priorities and the default free set."""
    body_names = list(FLOATING) + ["platform"] + (["tool"] if has_tool else [])
    body_names += [f"leg{i + 1}_{part}" for i in range(N_LEGS) for part in LEG_BODIES]
    bodies = tuple(dataclasses.replace(bd, name=nm) for bd, nm in zip(robot.bodies, body_names))
    names, priority = list(robot.names), np.ones(robot.n_params)
    for bd in bodies:
        for field, idx in zip(("a1", "a2", "a3", "d1", "d2", "d3"), bd.rows):
            if idx >= 0:
                names[idx] = f"{bd.name}.{field}"
                priority[idx] = _priority(bd.name, field)
    base_fixed, platform_fixed = rigid_coordinates(a), rigid_coordinates(b)
    free = [f"leg{i + 1}_slide.d3" for i in range(N_LEGS)]
    for part, fixed in (("base", base_fixed), ("ball", platform_fixed)):
        free += [f"leg{j // 3 + 1}_{part}.d{j % 3 + 1}" for j in range(3 * N_LEGS) if j not in fixed]
    return robot.replace(bodies=bodies, names=tuple(names), priority=priority).with_free(free)


def _priority(body: str, field: str) -> float:
    """Identification priority (seed 001 §4): 5 leg offsets, 4 joint centres, 3 the universal-joint axis offset
    (u2.d1, between the two axes), 1 the other leg rows, 0 the floating chain, platform and tool frames."""
    part = body.partition("_")[2]
    if not body.startswith("leg"):
        return 0.0
    if part == "slide" and field == "d3":
        return 5.0
    if part in ("base", "ball") and field.startswith("d"):
        return 4.0
    return 3.0 if (part, field) == ("u2", "d1") else 1.0


def hexapod_from_radii(rb: float, rp: float, base_gap_angle: float, platform_gap_angle: float, home_height: float,
                       **options) -> Robot:
    """The symmetric layout: base points on a circle of radius rb (z = 0) in three pairs centred at 0, 120 and 240
    degrees, base_gap_angle (rad) apart within a pair; platform points on a circle of radius rp in the platform's
    z = 0 plane in pairs centred at 60, 180 and 300 degrees, platform_gap_angle apart; leg j (0-based, k = j // 2,
    s = -1 for even j, +1 for odd) joins the base point at 120 k + s base_gap/2 to the platform point at
    120 k + s (60 - platform_gap/2) degrees. Home pose: platform parallel to the base at height home_height.
    options: those of `hexapod_robot` (stroke, tool, name)."""
    for value, what in ((rb, "rb"), (rp, "rp"), (home_height, "home_height")):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{what} must be a positive length (m), got {value!r}")
    k, s = np.arange(N_LEGS) // 2, np.where(np.arange(N_LEGS) % 2, 1.0, -1.0)
    base_angle = 2 * np.pi / 3 * k + s * base_gap_angle / 2
    platform_angle = 2 * np.pi / 3 * k + s * (np.pi / 3 - platform_gap_angle / 2)
    circle = lambda r, t: np.stack([r * np.cos(t), r * np.sin(t), np.zeros_like(t)], axis=1)  # noqa: E731
    return hexapod_robot(circle(rb, base_angle), circle(rp, platform_angle),
                         home_pose=(np.eye(3), np.array([0.0, 0.0, home_height])), **options)


__all__ = ["hexapod_from_radii", "hexapod_robot", "leg_lengths", "rigid_coordinates"]
