"""The Delta robot: nominal direct and inverse solutions (seed 004 §2.6) and a fast exact closure
of the Table 4.6 MCPC model.

Nominal model (§2.6, Figure 2.6): base radius rb, nacelle radius rn, actuated arm n, parallel
rods m, arms at azimuths psi_i; theta_i is the actuated angle below the horizontal, so the
elbow is b_i = [(rb + n cos th_i) cos psi_i, (rb + n cos th_i) sin psi_i, -n sin th_i]
(eq 2.114-2.115) and the nacelle stays parallel to the base.

- `direct`: Clavel's variation (eq 2.135-2.146): shift each elbow inwards by rn so that the three
  rod spheres meet in the nacelle centre P, express the spheres in a frame Fs with B'1 at the
  origin, B'2 on its 1 axis and B'3 in its 1-2 plane, and take the lower intersection.
- `inverse`: per arm, in the frame Fu whose 1 axis points to A_i (eq 2.147-2.158), the elbow
  lies on the circle of the arm and on the sphere of radius m around C_i; the elbow-out
  intersection is taken.
- Clavel's original solution (eq 2.118-2.134) and its breakdown ratio K_crit: `jaxcal.closure.clavel`.
- `open_loop_vector` / `open_loop_columns`: the open-loop Jacobian check of §2.4.3 (210 x 124).

Closure of the full 30-body MCPC model (Table 4.6, `jaxcal/robots/data/delta.yaml`): every rod
but the first ends in a universal joint whose centre does not move with the joint angles (bodies
16, 19, 22, 25, 28 sit on the elbow axis), so its rod end sweeps a sphere of radius |d_rod|
around that centre. The 20 free joints therefore reduce to the 5 joints of rod 1 (universal
5-6, ball 7-8-9, which carry the nacelle) under 5 sphere conditions |o_closure - c_k| = L_k:
a square system solved by Newton from the nominal direct solution of the robot's own dimensions
(`DeltaClosure.geometry`; any arm azimuths, `jaxcal.robots.delta_builder` writes the table from them).
The other rods' universal angles then follow by atan2 and their spin joints (17, 20, 23, 26, 29) do
not move anything (set to 0). Every sample is checked on the whole tree: the 15 closure residuals (positions of
the spherical closure pairs) must have norm <= `CLOSURE_TOL` (the thesis' 1e-10), else the
sample is flagged. Derivatives come from the implicit function theorem: one Newton step taken
from the (gradient-stopped) converged point, dx/da = -J^-1 dF/da.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal import exported
from jaxcal.closure.core import Closure, ClosureSolution, euler_parameters, failed_pose, forward_closed, tree_frames
from jaxcal.closure.core import solve as solve_generic
from jaxcal.closure.track import CLOSED, OTHER_MODE, UNCLOSED, Tracked, track
from jaxcal.kin.model import joint_variables, take
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import principal_rotation
from jaxcal.linalg import solve_small
from jaxcal.loops import varying_with

CLOSURE_TOL = 1e-10  # closure residual norm above which a sample is infeasible (seed 004 §4.3)
NEWTON_STEPS = 12
NEWTON_TOL = 1e-12  # m; the final implicit step squares this
NEWTON_HALVINGS = 4  # a Newton step is halved until it lowers |F|, at most this many times
# The fast path is trusted only where its nacelle (rod 1's last frame) lies this close to the nacelle of the nominal
# direct-solution start: BRANCH_RADIUS in rotation angle (rad), BRANCH_DISTANCE in position (m). The other assembly
# modes turn the ball joint by ~2.5 rad or mirror the nacelle by metres. Measured on the nacelle frame, not on the
# joint angles: near the ball joint's gimbal lock (q8 ~ pi/2) the same nacelle is reached with q7 and q9 each turned
# by ~1.8 rad (Table 4.6 Delta, 1 mm errors, one of 125 random settings).
BRANCH_RADIUS = 0.5
BRANCH_DISTANCE = 0.1
TRACK_TOL = 1e-12  # m: residual norm each continuation corrector reaches
TRACKED_CHUNK = 8  # samples the continuation runs on at once (`tracked_samples`)


@dataclasses.dataclass(frozen=True)
class DeltaGeometry:
    """Nominal Delta dimensions (m) and arm azimuths psi (rad), in the order of the actuators (§2.6):
    base radius rb, nacelle radius rn, actuated arm n, rods m; each arm carries a parallelogram whose
    two rods sit at +-spread along the elbow axis (Table 4.6 rows 6, 16, ...: 0.15 m); tool is the
    tool point relative to the nacelle centre P in base axes (the nacelle stays parallel to the base)."""

    rb: float = 0.2805
    rn: float = 0.196
    n: float = 0.6
    m: float = 0.9
    psi: tuple = (0.0, -2.0 * np.pi / 3.0, 2.0 * np.pi / 3.0)
    spread: float = 0.15
    tool: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        for field in ("rb", "rn", "n", "m", "spread"):
            value = getattr(self, field)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"Delta geometry: {field} must be a positive length in m, got {value!r}")
        for field in ("psi", "tool"):
            values = np.asarray(getattr(self, field), dtype=float)
            if values.shape != (3,) or not np.all(np.isfinite(values)):
                raise ValueError(f"Delta geometry: {field} must be 3 finite numbers, got {getattr(self, field)!r}")
            object.__setattr__(self, field, tuple(float(v) for v in values))  # hashable: part of a static robot
        gaps = np.abs(np.angle(np.exp(1j * (np.array(self.psi) - np.roll(self.psi, 1)))))
        if np.min(gaps) < 1e-6:
            raise ValueError(f"Delta geometry: the arm azimuths psi must be distinct, got {self.psi!r} rad")


# The Canterbury Delta of Table 4.6: actuators 2, 3, 4 at psi = 0, -120, +120 deg.
NOMINAL = DeltaGeometry()


def _radial(psi):
    return jnp.stack([jnp.cos(psi), jnp.sin(psi), jnp.zeros_like(psi)], axis=-1)


def elbows(theta, g: DeltaGeometry = NOMINAL):
    """Elbow points B_i (3, 3), one row per arm (eq 2.114)."""
    psi = jnp.asarray(g.psi)
    r = g.rb + g.n * jnp.cos(theta)
    return jnp.stack([r * jnp.cos(psi), r * jnp.sin(psi), -g.n * jnp.sin(theta)], axis=-1)


def direct(theta, g: DeltaGeometry = NOMINAL):
    """Nacelle centre P (3,) for actuator angles theta (3,) and a feasibility flag (eq 2.135-2.146)."""
    theta = jnp.asarray(theta, dtype=jnp.float64)
    b = elbows(theta, g) - g.rn * _radial(jnp.asarray(g.psi))  # B'_i, eq 2.135
    e1 = b[1] - b[0]
    i_s = e1 / jnp.linalg.norm(e1)
    k_s = jnp.cross(e1, b[2] - b[0])
    k_s = k_s / jnp.linalg.norm(k_s)
    k_s = jnp.where(k_s[2] < 0, -k_s, k_s)  # 3 axis upwards whatever the order of the arms
    j_s = jnp.cross(k_s, i_s)
    a = e1 @ i_s  # sphere centres (0,0,0), (a,0,0), (b,c,0) in Fs, eq 2.139-2.141
    bb = (b[2] - b[0]) @ i_s
    c = (b[2] - b[0]) @ j_s
    p1 = a / 2.0
    p2 = c / 2.0 + (bb**2 - a * bb) / (2.0 * c)
    h2 = g.m**2 - p1**2 - p2**2
    ok = h2 >= 0.0
    p3 = -jnp.sqrt(jnp.where(ok, h2, 0.0))  # lower intersection, eq 2.144
    P = b[0] + p1 * i_s + p2 * j_s + p3 * k_s  # eq 2.145
    return P, ok


def inverse(P, g: DeltaGeometry = NOMINAL):
    """Actuator angles theta (3,) placing the nacelle centre at P (3,), and a feasibility flag
    (eq 2.147-2.158). In Fu the elbow is (rb + n cos th, 0, -n sin th) and |B - C| = m gives
    e cos th + c3 sin th = K / (2 n) with e = rb - c1, K = m^2 - n^2 - e^2 - c2^2 - c3^2."""
    P = jnp.asarray(P, dtype=jnp.float64)
    psi = jnp.asarray(g.psi)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    c1 = cp * P[0] + sp * P[1] + g.rn  # C_i in Fu (eq 2.148-2.149)
    c2 = -sp * P[0] + cp * P[1]
    c3 = P[2]
    e = g.rb - c1
    k = g.m**2 - g.n**2 - e**2 - c2**2 - c3**2
    rho = jnp.sqrt(e**2 + c3**2)
    cosine = k / (2.0 * g.n * rho)
    ok = jnp.all(jnp.abs(cosine) <= 1.0)
    phi = jnp.arctan2(c3, e)
    theta = phi + jnp.arccos(jnp.clip(cosine, -1.0, 1.0))  # elbow-out branch
    return jnp.arctan2(jnp.sin(theta), jnp.cos(theta)), ok


def grid(center=(0.0, 0.0, -1.0), spacing=0.1, n=5):
    """The n x n x n measurement/compensation grid of §4.4.2 (default 125 points, 400 mm cube)."""
    ax = (np.arange(n) - (n - 1) / 2.0) * spacing
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=-1) + np.asarray(center, float)


# -- closure of the Table 4.6 MCPC model -------------------------------------------------------
ACTUATORS = (2, 3, 4)
ROD1 = (5, 6, 7, 8, 9)  # universal 5-6, rod 7, ball 7-8-9; body 9 is the nacelle
NACELLE, TOOL = 9, 30
CLOSURES = (10, 11, 12, 13, 14)  # nacelle ends of rods 2-6 (spherical closures)
RODS = ((15, 16, 17), (18, 19, 20), (21, 22, 23), (24, 25, 26), (27, 28, 29))  # universal + rod end
R_NACELLE = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # nominal nacelle frame, Rz(-pi/2)
_BALL = principal_rotation(0, np.pi / 2) @ principal_rotation(1, -np.pi / 2)  # constant part of the ball joint 7-8-9


def rod_ends(g: DeltaGeometry = NOMINAL) -> np.ndarray:
    """Nacelle ends of rods 1-6 relative to the nacelle centre P, base axes (6, 3): arm i's parallelogram
    ends at rn (cos psi_i, sin psi_i, 0) +- spread (-sin psi_i, cos psi_i, 0) (radial and elbow-axis
    directions, eq 2.135); rods 1, 2 on arm 1 (+, -), 3, 4 on arm 2, 5, 6 on arm 3."""
    psi = np.repeat(np.asarray(g.psi), 2)
    side = np.tile([1.0, -1.0], 3)[:, None]
    radial = np.stack([np.cos(psi), np.sin(psi), np.zeros(6)], axis=-1)
    axis = np.stack([-np.sin(psi), np.cos(psi), np.zeros(6)], axis=-1)
    return g.rn * radial + side * g.spread * axis


def nacelle_local(v, g: DeltaGeometry = NOMINAL) -> np.ndarray:
    """Points P + v (v (..., 3) in base axes) in the nacelle frame, body 9 of Table 4.6: origin at rod 1's
    end, axes R_NACELLE while the nacelle is parallel to the base."""
    return np.asarray(v) @ R_NACELLE - R_NACELLE.T @ rod_ends(g)[0]


def check_structure(robot):
    """Raise if `robot` is not laid out as Table 4.6 (the closure below relies on that layout)."""
    if len(robot.bodies) != 30 or robot.tip != TOOL - 1:
        raise ValueError(f"robot {robot.name!r} is not the 30-body Delta model of Table 4.6")
    for k, body in enumerate(robot.bodies, start=1):
        want = 2 if k in CLOSURES else (3 if k in (1, TOOL) else 0)
        if body.kind != want or bool(body.inputs) != (k in ACTUATORS):
            raise ValueError(f"robot {robot.name!r}, body {k}: type {body.kind} does not match Table 4.6")


def _statics(robot, a):
    """The parameter rows (a1, a2, a3, d1, d2, d3) of all 30 bodies, (30, 6) (unused entries read 0): what every body
    transform is built from (`_local`)."""
    a_ext = jnp.append(jnp.asarray(a, dtype=jnp.float64), 0.0)
    return {"rows": a_ext[np.array([b.rows for b in robot.bodies])]}


def _row(st, k):
    return st["rows"][k - 1]


def _local(st, k, qk=0.0):
    """Transform(s) of body k (an int or an array of body numbers) relative to the parent, with joint value(s) qk
    added to a3: T_k = [V_k, t_k] Rz(a3_k + q_k) Trans(0, 0, d3_k) with V_k = Rx(a1) Ry(a2), t_k = V_k (d1, d2, 0) (the
    MCPC transform of `jaxcal.kin.conventions.mcpc_frame`), multiplied out.

    Built for those bodies alone from their rows: a fit's reverse pass, sample by sample, then carries cotangents of
    their six parameters, not of every body's V and t (Delta, 125 positions: residuals and Jacobian 4.9 -> 4.3 ms)."""
    return _frame_parts(st["rows"][np.asarray(k) - 1], qk)[0]


def _frame_parts(row, qk):
    """(T, (v0, v1, v2)): the MCPC frame of `_local` for parameter row(s) (..., 6) and joint value(s) qk, and the
    columns of V = Rx(a1) Ry(a2) (the axes `_local_twists` reads its twists from)."""
    c1, s1, c2, s2 = jnp.cos(row[..., 0]), jnp.sin(row[..., 0]), jnp.cos(row[..., 1]), jnp.sin(row[..., 1])
    v0 = jnp.stack([c2, s1 * s2, -c1 * s2], axis=-1)  # the columns of V = Rx(a1) Ry(a2)
    v1 = jnp.stack([jnp.zeros_like(c1), c1, s1], axis=-1)
    v2 = jnp.stack([s2, -s1 * c2, c1 * c2], axis=-1)
    angle = row[..., 2] + qk
    c, s = jnp.cos(angle)[..., None], jnp.sin(angle)[..., None]
    R = jnp.stack([v0 * c + v1 * s, v1 * c - v0 * s, v2], axis=-1)
    return Pose(R, v0 * row[..., 3:4] + v1 * row[..., 4:5] + row[..., 5:6] * v2), (v0, v1, v2)


def _composed(f: Pose, g: Pose) -> Pose:
    """f o g (`Pose.compose`, broadcast over leading axes) with the 3 x 3 products written as products summed: XLA:CPU
    fuses those with their neighbours, where it compiles each dot as a kernel of its own (the Delta's fit program:
    285 -> 200 kernels compiled apart, 163k -> 139k lines of LLVM IR)."""
    R = jnp.sum(f.R[..., :, :, None] * g.R[..., None, :, :], axis=-2)
    return Pose(R, _applied(f, g.p))


def _applied(f: Pose, x):
    """Points x (..., 3) of frame f in its parent's frame, f.p + f.R x (`Pose.apply`, as a product summed)."""
    return f.p + jnp.sum(f.R * x[..., None, :], axis=-1)


def _fixed(robot, st, q):
    """Everything that does not depend on the free joints: actuated arm frames, the elbow frame
    of rod 1 at zero joint angle, and for rods 2-6 the elbow frames R_pre at zero angle, the
    universal centres c_k and the rod lengths L_k."""
    arms = _composed(_local(st, 1), _local(st, np.array(ACTUATORS), q))  # (3,) frames
    rod_arm = np.array([ACTUATORS.index(robot.bodies[r[0] - 1].parent + 1) for r in RODS])
    parents = Pose(arms.R[rod_arm], arms.p[rod_arm])
    f1 = _composed(parents, _local(st, np.array([r[0] for r in RODS])))
    f2 = _composed(f1, _local(st, np.array([r[1] for r in RODS])))
    ends = st["rows"][np.array([r[2] for r in RODS]) - 1]
    i1 = ACTUATORS.index(robot.bodies[ROD1[0] - 1].parent + 1)
    arm1 = Pose(arms.R[i1], arms.p[i1])
    return {"arm1": arm1, "elbow1": _composed(arm1, _local(st, ROD1[0])), "pre": f1.R, "centres": f2.p,
            "lengths": jnp.hypot(ends[:, 3], ends[:, 4])}


def _chain(st, f, bodies, x):
    """Frames of a serial run of bodies from frame f with joint values x (one trig evaluation for
    the whole run: fewer kernels, a faster compile)."""
    locs = _local(st, np.array(bodies), jnp.stack(x))
    out = []
    for i in range(len(bodies)):
        f = _composed(f, Pose(locs.R[i], locs.p[i]))
        out.append(f)
    return out


def _nacelle(robot, st, fixed, x):
    """Frame of the last body of rod 1 reached by x: with x = (q5, q6, q7, q8, q9) the nacelle (body 9)."""
    return _chain(st, fixed["arm1"], ROD1[: len(x)], x)[-1]


def _closure_points(robot, st, nacelle):
    return _applied(nacelle, _local(st, np.array(CLOSURES)).p)


def _sphere_residual(robot, st, fixed, x):
    """F(x) = |o_k - c_k| - L_k for the five nacelle closure points (m)."""
    pts = _closure_points(robot, st, _nacelle(robot, st, fixed, x))
    return jnp.linalg.norm(pts - fixed["centres"], axis=-1) - fixed["lengths"]


def _universal_angles(R_pre, u):
    """Joint angles (qa, qb) of a universal joint whose rod direction is Rz(qa) Rx(pi/2) Rz(qb) e1
    = (cos qa cos qb, sin qa cos qb, sin qb) in the frame R_pre; u is a unit vector in the world."""
    v = R_pre.T @ u
    return jnp.arctan2(v[1], v[0]), jnp.arctan2(v[2], jnp.hypot(v[0], v[1]))


def _start(robot, st, q, fixed):
    """Rod-1 joint values from the nominal direct solution of the robot's own geometry (nacelle centre
    P, nacelle parallel to the base, rod 1's end o9 = P + `rod_ends`[0]): universal angles from the rod
    direction, ball angles from the nacelle orientation (R6^T R9 C^T = Rz(q7) Ry(-q8) Rx(-q9), a Z-Y-X
    decomposition)."""
    g = robot.closure.geometry
    theta = q + jnp.stack([_row(st, k)[2] for k in ACTUATORS])
    P, ok = direct(theta, g)
    o9 = P + rod_ends(g)[0]
    f6 = _composed(fixed["elbow1"], _local(st, ROD1[1]))
    u = o9 - f6.p
    q5, q6 = _universal_angles(fixed["elbow1"].R, u / jnp.linalg.norm(u))
    f6 = _nacelle(robot, st, fixed, (q5, q6))  # frame 6 with the solved universal angles
    N = f6.R.T @ jnp.asarray(R_NACELLE) @ jnp.asarray(_BALL).T
    q7 = jnp.arctan2(N[1, 0], N[0, 0])
    q8 = jnp.arctan2(N[2, 0], jnp.hypot(N[2, 1], N[2, 2]))
    q9 = -jnp.arctan2(N[2, 1], N[2, 2])
    return jnp.stack([q5, q6, q7, q8, q9]), ok


def _residual_and_jacobian(robot, st, fixed, x):
    """F(x) and its Jacobian dF/dx. Each rod-1 joint j turns about its axis z_j through o_j, so
    a nacelle point moves by z_j x (p - o_j) and dF_k/dq_j = n_k . (z_j x (p_k - o_j)) with n_k
    the unit rod direction (the geometric Jacobian; a test checks it against jax.jacfwd)."""
    frames = _chain(st, fixed["arm1"], ROD1, x)
    axes = [f.R[:, 2] for f in frames]
    origins = [f.p for f in frames]
    pts = _closure_points(robot, st, frames[-1])
    d = pts - fixed["centres"]
    dist = jnp.linalg.norm(d, axis=-1)
    n = d / dist[:, None]
    moves = jnp.cross(jnp.stack(axes)[None, :, :], pts[:, None, :] - jnp.stack(origins)[None, :, :])  # (5 points, 5 joints, 3)
    return dist - fixed["lengths"], jnp.einsum("kc,kjc->kj", n, moves)


class NewtonState(NamedTuple):
    """Damped Newton on the sphere system (`_newton`): the current point x with F(x), the Newton direction
    d = J(x)^-1 F(x) and |F(x)|^2, the step t along -d that the next turn evaluates, the points taken so far (x0
    included), and whether the next turn is the first (it evaluates x0) or halves a step that did not lower |F|."""

    x: jnp.ndarray
    F: jnp.ndarray
    d: jnp.ndarray
    f: jnp.ndarray
    t: jnp.ndarray
    evals: jnp.ndarray
    first: jnp.ndarray
    halving: jnp.ndarray


def _newton_start(x0) -> NewtonState:
    """The state whose first turn evaluates x0."""
    inf = jnp.full((), jnp.inf, x0.dtype)
    return NewtonState(x0, jnp.full(len(ROD1), jnp.inf, x0.dtype), jnp.zeros_like(x0), inf, jnp.ones((), x0.dtype),
                       jnp.asarray(1), jnp.asarray(True), jnp.asarray(False))


def _newton_more(s: NewtonState):
    """Whether Newton goes on from s: its first turn, a step being halved, or max |F| above NEWTON_TOL (a non-finite F
    stops it) with fewer than NEWTON_STEPS points taken."""
    return s.first | s.halving | ((jnp.max(jnp.abs(s.F)) > NEWTON_TOL) & (s.evals < NEWTON_STEPS))


def _newton_turn(robot, st, fixed, s: NewtonState) -> NewtonState:
    """One evaluation: F and J at the trial point x - t d (x0 on the first turn). The point is taken where it lowers
    |F| or t has been halved NEWTON_HALVINGS times (or F is not finite there: Newton then stops); else t is halved.
    One evaluation site in the loop, not one before it, one for a full step and one in a loop of halvings: the fast
    path compiles in 0.86-1.02 s instead of 1.12-1.21 s (125 settings)."""
    p = jnp.where(s.first, s.x, s.x - s.t * s.d)
    F, J = _residual_and_jacobian(robot, st, fixed, p)
    f = jnp.sum(F**2)
    taken = s.first | ~(f >= s.f) | (s.t <= 0.5**NEWTON_HALVINGS)
    keep = lambda new, old: jnp.where(taken, new, old)  # noqa: E731
    return NewtonState(keep(p, s.x), keep(F, s.F), keep(solve_small(J, F), s.d), keep(f, s.f),
                       jnp.where(taken, 1.0, 0.5 * s.t), s.evals + (taken & ~s.first), jnp.asarray(False), ~taken)


def _newton(robot, st, fixed, x0):
    """Damped Newton on the square 5 x 5 sphere system until max |F| <= NEWTON_TOL (at most NEWTON_STEPS points
    taken): (x, max |F| at x, points taken). Each step is x - t J^-1 F with t = 1 halved until |F| falls (at most
    NEWTON_HALVINGS times, `_newton_turn`): full steps near a root, so quadratic convergence there, and no
    divergence from a start outside Newton's basin (near the ball joint's gimbal lock plain Newton left 8 steps at
    |x - x0| ~ 3.8e3 rad where the damped one closed in 9)."""
    s = jax.lax.while_loop(_newton_more, lambda s: _newton_turn(robot, st, fixed, s), varying_with(x0, _newton_start(x0)))
    return s.x, jnp.max(jnp.abs(s.F)), s.evals


def _homotopy_residual(robot, x, st_fixed):
    """F(x) of `_sphere_residual` for the pair (st, fixed) of `_homotopy_path`."""
    return _sphere_residual(robot, *st_fixed, x)


def _homotopy_path(robot, a, q):
    """t -> (st, fixed) along the path `track` follows from the nominal branch (seed 004 §2.4, made robust): what
    the sphere conditions read (`_sphere_residual`: rod 1's rows, the arm frame rod 1 hangs from, the universal
    centres and rod lengths of rods 2-6), moved linearly from the nominal robot's (t = 0) to the robot's with
    parameters a (t = 1), both at actuator joints q. Linear in t, so its derivative is the difference of the ends
    and `track` differentiates `_sphere_residual` alone."""
    ends = [(st, _fixed(robot, st, q)) for st in (_statics(robot, jnp.asarray(robot.nominal_np)), _statics(robot, a))]
    return lambda t: jax.tree_util.tree_map(lambda u, v: u + t * (v - u), *ends)


def _track(robot, a, q, x0, active=True) -> Tracked:
    """The continuation of one setting q from the nominal robot's closed configuration near x0 (`track`)."""
    return track(functools.partial(_homotopy_residual, robot), x0, TRACK_TOL, active=active, at=_homotopy_path(robot, a, q))


def _rod_angles(robot, st, fixed, nacelle):
    """Universal angles (qa (5,), qb (5,)) of rods 2-6 pointing each rod end at its nacelle closure
    point (as `_universal_angles`)."""
    u = _closure_points(robot, st, nacelle) - fixed["centres"]
    v = jnp.einsum("kji,kj->ki", fixed["pre"], u)  # R_pre^T u per rod
    return jnp.arctan2(v[:, 1], v[:, 0]), jnp.arctan2(v[:, 2], jnp.hypot(v[:, 0], v[:, 1]))


def closure_error(robot, st, q, nacelle, rods):
    """Norm of the 15 spherical-closure position residuals: each nacelle closure point against
    the end of its rod, built joint by joint (elbow at the actuated arm, universal angles
    `rods`, spin joint at 0)."""
    base = _local(st, 1)
    arms = {k: base.compose(_local(st, k, q[i])) for i, k in enumerate(ACTUATORS)}
    pts = _closure_points(robot, st, nacelle)
    res = []
    for k, (e1, e2, end) in enumerate(RODS):
        f = arms[robot.bodies[e1 - 1].parent + 1]
        f = f.compose(_local(st, e1, rods[0][k])).compose(_local(st, e2, rods[1][k])).compose(_local(st, end))
        res.append(pts[k] - f.p)
    return jnp.linalg.norm(jnp.stack(res))


def structure_ok(robot, st):
    """True when the fixed entries the reduction relies on hold: the universal joints of rods 2-6
    are perpendicular and centred on the elbow axis (rows 16, 19, ...: a1 = pi/2, a2 = a3 = d1 = 0)
    and the rod ends lie on the rod axis (rows 17, 20, ...: a1 = a2 = d2 = 0)."""
    dev = []
    for _, e2, end in RODS:
        r2, r3 = _row(st, e2), _row(st, end)
        dev += [r2[0] - np.pi / 2, r2[1], r2[2], r2[3], r3[0], r3[1], r3[4]]
    return jnp.max(jnp.abs(jnp.stack(dev))) <= 1e-12


def _near(nacelle: Pose, start: Pose):
    """Whether two nacelle frames lie within BRANCH_DISTANCE (m) and BRANCH_RADIUS (rotation angle, rad) of each
    other; the angle is 2 asin(|R - R0|_F / sqrt(8)), accurate at small angles."""
    chord = jnp.linalg.norm(nacelle.R - start.R) / np.sqrt(8.0)
    angle = 2.0 * jnp.arcsin(jnp.minimum(chord, 1.0))
    return (jnp.linalg.norm(nacelle.p - start.p) <= BRANCH_DISTANCE) & (angle <= BRANCH_RADIUS)


def _fast_single(robot, a, q):
    """The fast path for one actuator vector q (3,) (a, q without derivative): the nominal
    direct-solution start x0, Newton's result, whether the fast path is trusted (closed, and its nacelle `_near`
    the start's, i.e. on the nominal branch), whether it closed at all, whether the
    reduction applies (`structure_ok`, nominal direct solution feasible), and the points Newton evaluated."""
    st = _statics(robot, a)
    fixed = _fixed(robot, st, q)
    x0, ok_start = _start(robot, st, q, fixed)
    x_fast, err_fast, k_fast = _newton(robot, st, fixed, x0)
    valid = ok_start & structure_ok(robot, st)
    closes = valid & (err_fast <= NEWTON_TOL) & jnp.all(jnp.isfinite(x_fast))
    fast_ok = closes & _near(_nacelle(robot, st, fixed, x_fast), _nacelle(robot, st, fixed, x0))
    return jnp.where(jnp.isfinite(x0), x0, 0.0), x_fast, fast_ok, closes, valid, k_fast


def free_joints(robot, a, qj):
    """Rod-1 joints x (N, 5) closing the Delta at actuator joints qj (N, 3), without derivative, and
    per sample (on the nominal branch, closes elsewhere only, iterations).

    The fast path (Newton from the nominal direct solution) is kept where it closes on the nominal
    branch; every other sample goes through the general path, `jaxcal.closure.track`'s continuation
    from the nominal robot's closed configuration at the same setting, run on those samples only
    (`tracked_samples`)."""
    a, qj = jax.lax.stop_gradient(a), jax.lax.stop_gradient(qj)
    x0, x_fast, fast_ok, closes, valid, k_fast = jax.vmap(functools.partial(_fast_single, robot, a))(qj)
    need = valid & ~fast_ok
    tracked = tracked_samples(lambda qi, xi, act: _track(robot, a, qi, xi, act), qj, x0, need)
    x = jnp.where(fast_ok[:, None], x_fast, tracked.theta)
    finite = jnp.all(jnp.isfinite(x), axis=-1, keepdims=True)
    on_branch = fast_ok | tracked.reached
    return jnp.where(finite, x, x0), on_branch, closes & ~on_branch, k_fast + tracked.steps


def tracked_samples(run, qj, x0, need) -> Tracked:
    """`run(q, x0, active)` (the continuation of one sample) on the samples `need` selects, TRACKED_CHUNK at a
    time; the others keep x0 (not reached, 0 steps).

    The samples that need it are gathered first: a vmapped continuation steps every lane until its slowest
    lane ends, so run over the whole batch it costs the batch size times the longest path. Delta, 125
    samples of which the fast path missed 2 (one LM step from the frames-only fit): 69 ms over the batch,
    1.5 ms over those two alone."""
    n = need.shape[0]
    count = jnp.sum(need)
    order = jnp.concatenate([jnp.argsort(~need, stable=True), jnp.full(TRACKED_CHUNK, n)])  # needing first, then padding
    lane = jnp.arange(TRACKED_CHUNK)
    out = Tracked(x0, jnp.zeros(n, bool), jnp.zeros(n, jnp.int32), jnp.zeros(n, bool))

    def chunk(state):
        start, acc = state
        idx = jax.lax.dynamic_slice(order, (start,), (TRACKED_CHUNK,))
        active = start + lane < count
        got = jax.vmap(run)(jnp.take(qj, idx, axis=0, mode="clip"), jnp.take(x0, idx, axis=0, mode="clip"), active)
        got = got._replace(steps=got.steps.astype(jnp.int32))
        keep = jnp.where(active, idx, n)  # inactive lanes write nowhere
        return start + TRACKED_CHUNK, jax.tree_util.tree_map(lambda a, g: a.at[keep].set(g, mode="drop"), acc, got)

    return jax.lax.while_loop(lambda state: state[0] < count, chunk, varying_with(x0, (jnp.asarray(0, order.dtype), out)))[1]


def _turned(nacelle: Pose, frames, dx) -> Pose:
    """The nacelle after rod 1's joints turn by dx (5,) from where `frames` (their frames there, without derivative)
    were taken, to first order: joint j turns it about its axis z_j through o_j, so by the angular velocity
    w = sum_j dx_j z_j about the moment sum_j dx_j z_j x o_j. One chain evaluation (at x_star) serves the closure
    residual and the tool, where evaluating the chain again at x_star + dx would double the fits' reverse pass;
    dx is ~1e-12 rad at a closed sample, so the second-order term is ~1e-24."""
    z = jnp.stack([f.R[:, 2] for f in frames])
    o = jnp.stack([f.p for f in frames])
    w = dx @ z
    v = -(dx[:, None] * jnp.cross(z, o)).sum(axis=0)
    return Pose(nacelle.R + jnp.cross(w, nacelle.R, axisa=0, axisb=0, axisc=0), nacelle.p + jnp.cross(w, nacelle.p) + v)


def _finish_single(robot, a, q, x_star, on_branch, elsewhere):
    """Closed Delta for one actuator vector q (3,) from the solved rod-1 joints x_star: (rod-1
    joints x (5,), rod angles, tool Pose, ok, closure residual norm, status). x is differentiable in
    a and q by the implicit function theorem (one Newton step from the gradient-stopped x_star).

    With `structure_ok`, the closure residual of pair k (nacelle point minus rod end, the rod
    pointed at the point) has norm |F_k|, so |F| is the norm of all 15 closure residuals
    (a test checks this against `closure_error` on the whole tree)."""
    st = _statics(robot, a)
    fixed = _fixed(robot, st, q)
    st_sg, fixed_sg = jax.tree_util.tree_map(jax.lax.stop_gradient, (st, fixed))
    x_star = jax.lax.stop_gradient(x_star)
    F_star, J = _residual_and_jacobian(robot, st_sg, fixed_sg, x_star)
    # the zero step dx = -J^-1 F(x_star), which carries dx/d(a, q); J^-1 is formed without derivative, so a reverse
    # pass meets one 5 x 5 product, not the elimination's pivoting
    at_star = _nacelle(robot, st, fixed, x_star)
    pts = _closure_points(robot, st, at_star)
    dx = -solve_small(J, jnp.eye(J.shape[0], dtype=J.dtype)) @ (jnp.linalg.norm(pts - fixed["centres"], axis=-1) - fixed["lengths"])
    x = x_star + dx
    err = jnp.linalg.norm(F_star)
    err = jnp.where(jnp.isfinite(err), err, jnp.inf)
    ok = on_branch & (err <= CLOSURE_TOL)
    # turned only where closed (dx ~1e-12): an unclosed sample's dx may be of any size, and its penalty pose
    # (`failed_pose`) must stay near the robot, as the chain at x_star is, not run off along a first-order turn
    nacelle = _turned(at_star, _chain(st_sg, fixed_sg["arm1"], ROD1, x_star), jnp.where(ok, dx, 0.0))
    rods = _rod_angles(robot, st, fixed, nacelle)
    status = jnp.where(ok, CLOSED, jnp.where(elsewhere, OTHER_MODE, UNCLOSED))
    return x, rods, _composed(nacelle, _local(st, TOOL)), ok, err, status


# -- the fits' Jacobian from parameter twists -------------------------------------------------------------------
def _local_twists(rows, q):
    """The local frames (Pose of (B, 3, 3)/(B, 3)) of bodies with parameter rows `rows` (B, 6) and joint values q (B,),
    and the parent-frame twists (omega, v) (B, 6 row entries, 6) of their rows (`jaxcal.kin.twists`), in closed form:
    with T = (V Rz(a3 + q), V d), V = Rx(a1) Ry(a2) = [v0 v1 v2], a1 turns about e1, a2 about v1 and a3 about v2
    through the origin of T (v = -omega x p), and d1, d2, d3 translate along v0, v1, v2. The joint value's twist is
    a3's."""
    frames, (v0, v1, v2) = _frame_parts(rows, q)
    nil = jnp.zeros_like(v0)
    e1 = nil.at[:, 0].set(1.0)
    omega = jnp.stack([e1, v1, v2, nil, nil, nil], axis=1)
    v = jnp.stack([nil, nil, -jnp.cross(v2, frames.p), v0, v1, v2], axis=1)
    return frames, jnp.concatenate([omega, v], axis=-1)


@functools.lru_cache(maxsize=8)
def _twist_tables(robot):
    """Static tables of `tool_and_twists`: for each parameter i its (body, row entry) slot k * 6 + f in the (30 * 6)
    twists (-1: none), and whether its body lies on the path of the tool, of each nacelle closure point (5) and of
    each rod's universal centre (5); for each of those the same per actuator; one-hot (5, 2, P) of the parameters of
    the rods' end rows d1, d2 (lengths L_k = hypot(d1, d2))."""
    slot = [-1] * robot.n_params
    for k, body in enumerate(robot.bodies):
        for f, i in enumerate(body.rows):
            if i >= 0:
                slot[i] = k * 6 + f

    def path(b):  # body numbers from b up to the base
        out = set()
        while b >= 1:
            out.add(b)
            b = robot.bodies[b - 1].parent + 1
        return out

    tips = [TOOL] + list(CLOSURES) + [rod[1] for rod in RODS]
    on = np.zeros((len(tips), robot.n_params))
    for t, tip in enumerate(tips):
        bodies = path(tip)
        for k, body in enumerate(robot.bodies, start=1):
            for i in body.rows:
                if i >= 0 and k in bodies:
                    on[t, i] = 1.0
    arms = np.array([[float(k in path(tip)) for k in ACTUATORS] for tip in tips])
    ends = np.zeros((len(RODS), 2, robot.n_params))  # one-hot: the parameter of each rod end's d1, d2
    for k, rod in enumerate(RODS):
        for f, i in enumerate(robot.bodies[rod[2] - 1].rows[3:5]):
            if i >= 0:
                ends[k, f, i] = 1.0
    return tuple(slot), on, arms, ends


def tool_and_twists(robot, a, q, pre, held=False):
    """(tool, Xi) of one sample from its presolved closure pre = (x_star, on_branch, elsewhere) (`presolve`): the
    tool pose (`forward_presolved`'s to round-off; a sample that does not close is moved by `failed_pose`) and the
    world twist (omega, v) of the tool per robot parameter, Xi (P, 6) (0 where the sample does not close: its
    penalty pose has no derivative; held, traced: 0, not computed). One pass over the 30 bodies' frames gives both
    (seed 004 eq 2.65 by parameter twists, `jaxcal.kin.twists`); a fit's Jacobian is then built as an open chain's
    (`jaxcal.fit.core.open_residual_and_jacobian`), with no reverse pass through the closure. Against reverse mode
    through `forward_presolved` (Delta, 125 positions, both programs' LLVM IR 197k -> 139k lines, 350 -> 200 kernels
    compiled apart): the first `identify` 10.4-10.5 -> 7.6-7.7 s on a slow hour of this 2-core CPU, the same run
    time (docs/benchmarks.md, twenty-seventh session).

    A parameter of body b moves every frame below b by the world twist xi of its row entry (`_local_twists` carried
    to the world by b's parent frame). The sphere conditions F_k = |o_k - c_k| - L_k (`_sphere_residual`: nacelle
    point o_k, universal centre c_k at zero universal angles as `_fixed`, n_k = (o_k - c_k) / |o_k - c_k|) move by
    n_k . (do_k - dc_k) - dL_k, a point p by omega x p + v for each xi on its path; rod 1's joint x_m turns them by
    its a3 twist zeta_m, so J = dF/dx = [n_k . (zeta_m at o_k)] (`_residual_and_jacobian`'s geometric Jacobian). The
    tool moves by the xi on its path (base, arm 1, rod 1, nacelle, tool) and by dx/da = -J^-1 dF/da (the implicit
    function theorem, eq 2.65). The tool itself is the nacelle at x_star turned by the Newton step dx = -J^-1 F
    (`_turned`), as in `_finish_single`. A gain moves the actuator joints (dq/da by forward mode), each turning its
    arm by its a3 twist. Static indices throughout (slices, one-hot products): under vmap a scatter or gather at
    traced positions is a loop over the batch."""
    x_star, on_branch = jax.lax.stop_gradient(pre[0]), pre[1]
    st = _statics(robot, a)
    qj = joint_variables(robot, a, q)
    joints = jnp.concatenate([jnp.zeros(ACTUATORS[0] - 1, a.dtype), qj, x_star, jnp.zeros(len(robot.bodies) - ROD1[-1], a.dtype)])
    locs, xi = _local_twists(st["rows"], joints)
    base = Pose(jnp.eye(3, dtype=a.dtype), jnp.zeros(3, a.dtype))
    worlds = {0: base}
    for k, body in enumerate(robot.bodies, start=1):  # parents before children (the table's order)
        worlds[k] = _composed(worlds[body.parent + 1], Pose(locs.R[k - 1], locs.p[k - 1]))
    parents = [worlds[body.parent + 1] for body in robot.bodies]
    R_par, p_par = jnp.stack([f.R for f in parents]), jnp.stack([f.p for f in parents])
    omega = jnp.sum(R_par[:, None] * xi[:, :, None, :3], axis=-1)
    v = jnp.sum(R_par[:, None] * xi[:, :, None, 3:], axis=-1) + jnp.cross(p_par[:, None, :], omega)
    world = jnp.concatenate([omega, v], axis=-1)  # (bodies, 6 row entries, 6)

    def moved(twists, points):  # twists (K, ..., 6) at points (K, 3): the points' velocities (K, ..., 3)
        return jnp.cross(twists[..., :3], points[:, None, :]) + twists[..., 3:]

    o = jnp.stack([worlds[k].p for k in CLOSURES])
    c = jnp.stack([worlds[rod[1]].p for rod in RODS])
    ends = jnp.stack([st["rows"][rod[2] - 1, 3:5] for rod in RODS])  # (5, 2): d1, d2 of the rod ends
    lengths = jnp.linalg.norm(ends, axis=-1)
    dist = jnp.linalg.norm(o - c, axis=-1)
    F, n = dist - lengths, (o - c) / dist[:, None]
    zeta = world[ROD1[0] - 1:ROD1[-1], 2]  # (5, 6): rod 1's joints' a3 twists
    J = jnp.sum(n[:, None, :] * moved(jnp.broadcast_to(zeta, (len(CLOSURES),) + zeta.shape), o), axis=-1)
    J_inv = solve_small(J, jnp.eye(len(ROD1), dtype=a.dtype))
    err = jnp.linalg.norm(F)
    ok = on_branch & (jnp.where(jnp.isfinite(err), err, jnp.inf) <= CLOSURE_TOL)
    dx = jnp.where(ok, -J_inv @ F, 0.0)
    nacelle = _turned(worlds[NACELLE], [worlds[k] for k in ROD1], dx)
    tool = failed_pose(_composed(nacelle, Pose(locs.R[TOOL - 1], locs.p[TOOL - 1])), ok)

    def twists():
        slot, on, arms, end_params = _twist_tables(robot)
        per_param = take(world.reshape(-1, 6), slot)  # (P, 6): each parameter's twist (its body's paths: `on`)
        # F_k moves by n_k . (omega x p + v) = (p x n_k, n_k) . (omega, v) at p = o_k and c_k: each path's twists
        # against one wrench, not its points' velocities
        W = jnp.concatenate([jnp.concatenate([jnp.cross(o, n), n], axis=-1),
                             -jnp.concatenate([jnp.cross(c, n), n], axis=-1)])  # (10, 6): at o_k, then at c_k
        dF = on[1:] * (W @ per_param.T)  # (10, P)
        Xi = on[0][:, None] * per_param
        if robot.gains is not None:  # joint values move with the parameters (seed 001 eq 4), each turning its arm
            dq = jax.jacfwd(lambda b: joint_variables(robot, b, q))(a)  # (3, P)
            arm = world[ACTUATORS[0] - 1:ACTUATORS[-1], 2]  # (3, 6): the actuator joints' twists
            dF = dF + jnp.einsum("tj,jp,tj->tp", arms[1:], dq, W @ arm.T)
            Xi = Xi + jnp.einsum("j,jp,jk->pk", arms[0], dq, arm)
        dL = jnp.sum((ends / lengths[:, None])[:, :, None] * end_params, axis=1)
        dF = dF[:len(CLOSURES)] + dF[len(CLOSURES):] - dL
        return jnp.where(ok, Xi - (J_inv @ dF).T @ zeta, 0.0)

    return tool, jax.lax.cond(held, lambda: jnp.zeros((robot.n_params, 6), a.dtype), twists)


def _flat(q):
    q = jnp.asarray(q, dtype=jnp.float64)
    return q.reshape(-1, q.shape[-1]), q.shape[:-1]


def _unflat(out, lead):
    return jax.tree_util.tree_map(lambda v: v.reshape(lead + v.shape[1:]), out)


@exported.jit(static_argnums=(0,))  # kept across processes (tracing it took 1.8-2.4 s)
def solve(robot, a, q) -> ClosureSolution:
    """Closure of the Table 4.6 Delta for actuator settings q (..., 3): free joints in the order
    of `FREE` (15,), closure residual norm, ok flag, Newton iterations (fast path + continuation) and
    status (`jaxcal.closure.track`: CLOSED, UNCLOSED or OTHER_MODE)."""
    a = jnp.asarray(a, dtype=jnp.float64)
    qf, lead = _flat(q)
    qj = jax.vmap(lambda qi: joint_variables(robot, a, qi))(qf)
    x_star, on_branch, elsewhere, steps = free_joints(robot, a, qj)

    def one(qi, xi, b, e, k):
        x, rods, _, ok, err, status = _finish_single(robot, a, qi, xi, b, e)
        theta = jnp.concatenate([x, jnp.stack(rods, axis=-1).ravel()])  # (q15, q16, q18, q19, ...)
        return ClosureSolution(theta, err, ok, k, status)

    return _unflat(jax.vmap(one)(qj, x_star, on_branch, elsewhere, steps), lead)


def _pose_vector(robot, a, q, pre):
    """(R.ravel(), p) of the tool (12,) and the closure flag as 0/1 (aux); pre = (x_star, on_branch,
    elsewhere) from `free_joints`."""
    _, _, tool, ok, _, _ = _finish_single(robot, a, q, *pre)
    return jnp.concatenate([tool.R.ravel(), tool.p]), ok.astype(jnp.float64)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _tool_vector(robot, a, q, pre):
    return _pose_vector(robot, a, q, pre)


@_tool_vector.defjvp
def _tool_vector_jvp(robot, primals, tangents):
    """Tangent of the tool pose from its per-sample Jacobian by reverse mode (12 cotangents instead
    of one forward pass per parameter): under `jax.jacfwd` over ~170 parameters the Jacobian is
    computed once per sample and contracted with every tangent. pre has no derivative."""
    a, q, pre = primals
    da, dq, _ = tangents
    vec, pullback, ok = jax.vjp(lambda a_, q_: _pose_vector(robot, a_, q_, pre), a, q, has_aux=True)
    Ja, Jq = jax.vmap(pullback)(jnp.eye(vec.shape[0]))
    return (vec, ok), (Ja @ da + Jq @ dq, jnp.zeros_like(ok))


@functools.partial(jax.jit, static_argnums=0)
def forward(robot, a, q) -> Pose:
    """Tool pose of the Table 4.6 Delta for actuator settings q (..., 3), closure solved inside.
    A sample that does not close is moved by `failed_pose` (as in `forward_closed`)."""
    a = jnp.asarray(a, dtype=jnp.float64)
    qf, lead = _flat(q)
    qj = jax.vmap(lambda qi: joint_variables(robot, a, qi))(qf)
    pre = free_joints(robot, a, qj)[:3]

    def one(qi, xi, b, e):
        vec, ok = _tool_vector(robot, a, qi, (xi, b, e))
        return failed_pose(Pose(vec[:9].reshape(3, 3), vec[9:]), ok > 0)

    return _unflat(jax.vmap(one)(qj, *pre), lead)


@functools.partial(jax.jit, static_argnums=0)
def presolve(robot, a, q):
    """The rod-1 joints closing the Delta at actuator settings q (..., 3), without derivative: (x_star, on_branch,
    elsewhere) of `free_joints`, per sample, for `forward_presolved`."""
    a = jax.lax.stop_gradient(jnp.asarray(a, dtype=jnp.float64))
    qf, lead = _flat(q)
    qj = jax.vmap(lambda qi: joint_variables(robot, a, qi))(qf)
    return _unflat(free_joints(robot, a, qj)[:3], lead)


def forward_presolved(robot, a, q, pre) -> Pose:
    """`forward` from the closure solved beforehand (`presolve` at the same a and q), differentiated by plain
    autodiff through the implicit step of `_finish_single` (forward or reverse mode).

    A fit differentiates it in reverse mode sample by sample (`jaxcal.fit.core.data_residual_and_jacobian`): the
    closure is solved once for the batch, then each sample's readings take as many reverse passes as they have
    components (3 for a position) instead of `forward`'s 12-row Jacobian contracted with every tangent. Seed 004
    Table 4.6 Delta, 125 positions, 166 parameters: residuals and Jacobian 14.9 -> 4.2 ms on this 2-core CPU."""
    a = jnp.asarray(a, dtype=jnp.float64)
    qf, lead = _flat(q)
    pre = jax.tree_util.tree_map(lambda v: v.reshape((-1,) + v.shape[len(lead):]), pre)
    qj = jax.vmap(lambda qi: joint_variables(robot, a, qi))(qf)

    def one(qi, xi, b, e):
        _, _, tool, ok, _, _ = _finish_single(robot, a, qi, xi, b, e)
        return failed_pose(tool, ok)

    return _unflat(jax.vmap(one)(qj, *pre), lead)


def closed(robot, a, q):
    """Per-sample flags: True where the Delta closes to CLOSURE_TOL."""
    return solve(robot, a, q).ok


@dataclasses.dataclass(frozen=True)
class DeltaClosure(Closure):
    """The generic closure description of the Table 4.6 Delta plus its fast path: `jc.forward`
    calls `forward(robot, a, q)` (start from the nominal direct solution of `geometry`, the robot's
    own dimensions, then Newton on the reduced square system); the generic LM of `jaxcal.closure`
    still works from `start` near the home setting."""

    geometry: DeltaGeometry = NOMINAL
    transposable = True  # its JVP is built from reverse-mode Jacobians
    twists = True  # a fit's Jacobian from the tool's parameter twists (`tool_and_twists`)
    xla_dots = True  # its Newton uses the geometric Jacobian: few dots to compile (`jaxcal.fit.core.xla_dots`)

    def serving(self, robot, a, free_mask=None):
        """The robot itself while the fixed entries the reduction relies on (`structure_entries`) hold in a
        and are not free; else the robot with the generic whole-tree closure (`general_robot`), which closes
        any geometry (the fast path would flag every sample). A traced a (inside a fit) is not checked: the
        fit's problem is set up with the serving robot (`jaxcal.fit.core.make_problem`)."""
        if isinstance(a, jax.core.Tracer):
            return robot
        off = reduction_breaks(robot, a, free_mask)
        if not off:
            return robot
        warnings.warn(f"{robot.name}: the Delta's fast closure needs {', '.join(off[:6])}{' ...' if len(off) > 6 else ''} "
                      "fixed at their Table 4.6 values (perpendicular universal joints on the elbow axis, rod ends on "
                      "the rod axis); they are off or free, so the generic whole-tree closure is used (slower to "
                      "compile and run)", stacklevel=3)
        return general_robot(robot)

    def forward(self, robot, a, q) -> Pose:
        served = self.serving(robot, a)
        return forward(robot, a, q) if served is robot else forward_closed(served, a, q)

    def solve(self, robot, a, q) -> ClosureSolution:
        served = self.serving(robot, a)
        return solve(robot, a, q) if served is robot else solve_generic(served, a, q)

    def presolve(self, robot, a, q):
        """`presolve` (robot: the serving robot, as in a fit's problem)."""
        return presolve(robot, a, q)

    def tool_and_twists(self, robot, a, q, pre, held=False):
        """`tool_and_twists` (robot: the serving robot, as in a fit's problem)."""
        return tool_and_twists(robot, a, q, pre, held)

    def forward_presolved(self, robot, a, q, pre) -> Pose:
        """`forward_presolved` (robot: the serving robot, as in a fit's problem)."""
        return forward_presolved(robot, a, q, pre)


STRUCTURE_TOL = 1e-12  # rad / m: how far a structure entry may be from its value for the reduction to hold


def structure_entries(robot) -> list[tuple[int, float]]:
    """(parameter index, value) of the fixed entries `structure_ok` checks, where the robot has them: rows
    16, 19, ... (a1 = pi/2, a2 = a3 = d1 = 0) and 17, 20, ... (a1 = a2 = d2 = 0)."""
    want = []
    for _, e2, end in RODS:
        want += [(robot.bodies[e2 - 1].rows[f], v) for f, v in ((0, np.pi / 2), (1, 0.0), (2, 0.0), (3, 0.0))]
        want += [(robot.bodies[end - 1].rows[f], 0.0) for f in (0, 1, 4)]
    return [(int(i), v) for i, v in want if i >= 0]


def reduction_breaks(robot, a, free_mask=None) -> list[str]:
    """Names of the structure entries that are off their value in a (by > STRUCTURE_TOL) or free in free_mask."""
    a = np.asarray(a, float)
    free = np.zeros(len(a), bool) if free_mask is None else np.asarray(free_mask, bool)
    return [robot.names[i] for i, v in structure_entries(robot) if abs(a[i] - v) > STRUCTURE_TOL or free[i]]


@functools.lru_cache(maxsize=8)
def general_robot(robot):
    """The Delta with the generic whole-tree closure (`jaxcal.closure.core`: continuation from the closed home
    configuration `start`) in place of the fast path: same parameters, any geometry. One object per robot: compiled
    functions take the robot as a static argument, which hashes by identity, so a new object at every call traced
    and compiled the generic closure again: ~30 s per `core.predicted` of a Delta off its structure entries, each
    compile adding ~5,000 memory mappings until LLVM aborted the process ("Unable to allocate section memory")."""
    c = robot.closure
    return robot.replace(closure=Closure(pairs=c.pairs, free=c.free, start=c.start))


def full_precision_nominal(robot, g: DeltaGeometry = NOMINAL):
    """The nominal parameters with the nacelle points 10-14 at full precision (Table 4.6 prints
    4 digits, ~4e-5 m off): the ends of rods 2-6 (`rod_ends`) in the nacelle frame (`nacelle_local`)."""
    a = np.array(robot.nominal_np)
    for body, local in zip(CLOSURES, nacelle_local(rod_ends(g)[1:], g)):
        a[robot.index(f"j{body}.d1")], a[robot.index(f"j{body}.d2")] = local[0], local[1]
    return jnp.asarray(a)


PAIRS = tuple((rod[2], c, "position") for c, rod in zip(CLOSURES, RODS))
FREE = ROD1 + tuple(b for rod in RODS for b in rod[:2])


@exported.jit(static_argnums=(0,))
def _home_closure(robot, a, q):
    """(theta_free in the order of FREE, ok) of the nominal model at one setting by the fast path alone:
    the nominal direct solution is exact there, so Newton closes at once and the continuation of `solve`
    (most of its compile time) is not needed; `ok` is `_finish_single`'s check on the whole tree."""
    qj = joint_variables(robot, a, q)
    _, x_fast, fast_ok, closes, _, _ = _fast_single(robot, a, qj)
    x, rods, _, ok, _, _ = _finish_single(robot, a, qj, x_fast, fast_ok, closes & ~fast_ok)
    return jnp.concatenate([x, jnp.stack(rods, axis=-1).ravel()]), ok


def with_delta_closure(robot, free=None, geometry: DeltaGeometry = NOMINAL):
    """The Table 4.6 robot with a `DeltaClosure` whose generic start is the closed home setting, whose
    fast path starts from the nominal direct solution of `geometry` (the dimensions the robot's table was
    written from), and (optionally) the free parameters given by name."""
    check_structure(robot)
    plain = robot.replace(closure=DeltaClosure(pairs=PAIRS, free=FREE, start=(0.0,) * len(FREE), geometry=geometry))
    theta, ok = _home_closure(plain, plain.nominal, plain.home)
    if not bool(ok):
        raise ValueError(f"robot {robot.name!r}: the Delta does not close at its home setting {plain.home_np}")
    start = tuple(float(v) for v in theta)
    out = robot.replace(closure=DeltaClosure(pairs=PAIRS, free=FREE, start=start, geometry=geometry))
    return out if free is None else out.with_free(free)


# -- the open-loop Jacobian of §2.4.3 ----------------------------------------------------------
def open_loop_vector(robot, a, qj, theta_free):
    """Position and Euler parameters of every body frame of the open tree, (7 n_bodies,) = (210,)
    for Table 4.6: the rows of the open-loop Jacobian D_p of eq 2.63-2.64, stacked over the frames."""
    f = tree_frames(robot, a, qj, theta_free)
    return jnp.concatenate([f.p, jax.vmap(euler_parameters)(f.R)], axis=1).ravel()


def open_loop_columns(robot) -> np.ndarray:
    """Indices of the 124 geometric parameters of §2.4.3: all 157 of Table 4.6 except the 18 joint
    settings a3 of the actuated and free joints (joint variables, not geometry) and the a1, a2, a3 of
    the five spherical closure frames 10-14 (a spherical closure has only its position, d1 d2 d3):
    23 x 5 + 5 x 3 + 2 x 6 = 142 model parameters (the count of Table 3.2), 142 - 18 = 124."""
    moving = set(ACTUATORS + FREE)

    def kept(name):
        body, part = name.split(".")
        k = int(body[1:])
        return not ((k in CLOSURES and part in ("a1", "a2", "a3")) or (k in moving and part == "a3"))

    return np.array([i for i, n in enumerate(robot.names) if kept(n)])


# -- Table 4.7: the thesis' identified models -------------------------------------------------
# (parameter, identified - perturbed for simulation 1, 2, 3 and the experiment), columns 4-7 of seed 004
# Table 4.7; perturbed = nominal with rod 26 20 mm longer (column 3). Rows "30,d2"/"30,d3" are our
# j30.d1/j30.d2 (docs/delta.md). OCR repairs: exponents lost in 26,d1 sim 1, 27,a1 sims 1-3 (taken as the
# column's usual e-5/e-6) and the mantissas "4.?e-7" (5,a1 sim 1), "2.?e-6" (13,d2 sim 1), "5.7e-?" (24,d1
# sim 1); the simulation-1 column is at most 4.6e-5 and none of these enter the experimental column.
TABLE_4_7 = [
    ("j2.a1", 2.9e-6, -4.4e-5, -1e-4, 9.4e-4), ("j2.a2", -5.2e-8, 8.9e-5, 2.2e-4, 3.7e-3),
    ("j2.a3", -6.1e-7, 1.7e-4, 3.5e-4, 4.4e-3), ("j2.d1", 1.5e-5, 3.1e-5, 3.8e-5, -1.1e-3),
    ("j2.d2", 2.8e-6, 4.8e-4, 9.6e-4, -3.1e-3), ("j3.a1", -4.6e-5, -8.8e-5, -1.7e-4, -1.2e-4),
    ("j3.a2", -3.3e-5, 7.6e-6, 1.7e-8, 1.2e-3), ("j3.a3", 1.6e-5, -7.8e-5, -1.4e-4, 2.1e-4),
    ("j3.d1", -6.1e-8, 2.2e-5, 1.4e-5, -1.7e-3), ("j3.d2", 4.8e-6, -1.4e-4, -2.7e-4, -1.8e-3),
    ("j4.a1", 2.7e-5, -2.7e-4, -5.4e-4, 8.9e-4), ("j4.a2", 2.5e-5, 4.8e-5, 1.2e-4, 6.2e-3),
    ("j4.a3", 9.9e-6, 3.2e-4, 6.2e-4, -8.8e-4), ("j4.d1", -3.6e-6, -3e-4, -5.9e-4, -4.8e-4),
    ("j4.d2", 2.8e-6, 4.5e-4, 9e-4, 1.1e-4), ("j5.a1", -4e-7, 9.9e-6, 1.7e-5, -7.3e-4),
    ("j5.a2", 4.6e-6, 4.7e-5, 1.1e-4, 5.5e-4), ("j5.d1", -3.4e-7, -3.5e-5, -1.1e-4, -1.5e-3),
    ("j5.d2", -4.9e-7, -6.6e-5, -1.1e-4, 4.9e-3), ("j7.d1", 1.2e-7, -5e-5, -8.9e-5, 3.2e-4),
    ("j10.a1", -2.1e-7, 9.1e-8, 3.6e-7, 1.2e-8), ("j10.a2", 4.5e-7, -1.2e-4, -2.4e-4, -4.8e-4),
    ("j10.d1", -2.2e-8, -3.5e-5, -8.2e-5, -1.4e-3), ("j10.d2", 1.4e-8, 1.1e-4, 2.2e-4, -2.8e-3),
    ("j10.d3", -1.7e-6, 4e-4, 8e-4, 1.6e-3), ("j11.a1", -9.4e-7, 3.7e-8, 7.5e-6, 3.5e-4),
    ("j11.a2", -2.2e-6, 9e-6, 1.8e-5, 8.5e-4), ("j11.d1", 5.3e-6, 4e-5, 1.3e-4, 5.1e-3),
    ("j11.d2", 1.4e-5, 1.4e-4, 2.7e-4, 4.4e-4), ("j11.d3", 5.5e-6, -2.3e-5, -4.6e-5, -2.1e-3),
    ("j12.a1", 1.5e-7, 5e-5, 9.6e-5, -1.6e-4), ("j12.a2", -5.3e-8, 2.9e-5, 5.5e-5, -9.1e-5),
    ("j12.d1", 1.4e-5, -5.5e-5, -1.4e-4, -2.3e-3), ("j12.d2", 9.4e-6, -1.2e-4, -2.5e-4, 1e-3),
    ("j12.d3", -3.8e-7, -1.2e-4, -2.3e-4, 3.7e-4), ("j13.a1", -2e-7, -2.2e-4, -4.4e-4, 1.2e-3),
    ("j13.a2", -1.5e-6, -2.9e-5, -5.7e-5, 1.6e-4), ("j13.d1", -8.9e-6, -3.8e-4, -7.6e-4, 4.9e-4),
    ("j13.d2", 2e-6, -4.4e-4, -9e-4, -6.9e-3), ("j13.d3", 3.8e-7, 5.2e-4, 1e-3, -2.8e-3),
    ("j14.a1", -1.7e-8, 1.1e-5, 2.1e-5, -4.8e-4), ("j14.a2", -6.9e-7, -6.5e-6, -1.2e-5, 2.7e-4),
    ("j14.d1", -2.7e-6, 2.5e-4, 5.3e-4, 2.9e-3), ("j14.d2", 7.1e-8, 6.7e-5, 1.3e-4, 1.6e-5),
    ("j14.d3", 5.4e-6, -6.9e-5, -1.3e-4, 2.9e-3), ("j15.a1", -2e-7, 5.2e-5, 1e-4, 3.6e-4),
    ("j15.a2", 7.6e-7, 3.9e-5, 8.9e-5, 1.4e-3), ("j15.d1", 4.7e-7, -1.2e-4, -2.6e-4, -3.7e-3),
    ("j15.d2", -3.1e-7, 3.5e-4, 6.9e-4, 2.4e-3), ("j17.d1", 1.4e-7, 3.8e-4, 7.7e-4, -7e-4),
    ("j18.a1", -2e-6, 1.2e-5, 2e-5, -4.6e-5), ("j18.a2", 9.1e-6, 1.1e-4, 2.2e-4, 1.4e-3),
    ("j18.d1", -1e-6, 1.5e-4, 3e-4, -2.2e-3), ("j18.d2", 1.4e-5, -7.7e-5, -1.3e-4, 2.8e-4),
    ("j20.d1", 8.6e-7, -6.3e-5, -8.7e-5, 9.6e-4), ("j21.a1", 2.2e-8, -7.8e-8, -1.6e-5, 1.1e-5),
    ("j21.a2", 8.7e-6, -6.2e-5, -1.3e-4, 1.6e-4), ("j21.d1", 1.4e-6, -1.1e-4, -2.5e-4, -2.1e-3),
    ("j21.d2", 1.4e-5, -5.2e-5, -1.1e-4, 7.3e-5), ("j23.d1", 1.3e-6, -6.5e-5, -1.4e-4, -1.4e-3),
    ("j24.a1", -1.3e-6, -1.1e-4, -2.1e-4, -1.6e-4), ("j24.a2", -4e-6, 1e-4, 2e-4, 3.2e-3),
    ("j24.d1", 5.7e-7, -1.1e-4, -2.3e-4, -3.4e-3), ("j24.d2", 8.3e-8, 7.1e-4, 1.4e-3, 1e-3),
    ("j26.d1", -1.8e-6, -4.2e-3, -8.4e-3, -1.4e-4), ("j27.a1", 2.5e-6, -2.7e-5, -5.8e-5, -3.8e-4),
    ("j27.a2", -3.6e-6, 2.9e-5, 7.5e-5, 1.3e-3), ("j27.d1", -6.1e-7, 6.7e-5, 1.2e-4, -3.2e-3),
    ("j27.d2", 8e-6, -1.8e-4, -3.8e-4, -2.5e-3), ("j29.d1", -1.5e-6, -2.3e-4, -4.5e-4, 1.8e-3),
    ("j30.a1", 2.9e-6, 1.5e-4, 3.1e-4, -9.1e-4), ("j30.a2", 2.6e-6, 1.2e-4, 2.4e-4, -7e-4),
    ("j30.d1", 1.9e-6, 2.7e-4, 5.3e-4, -2e-3), ("j30.d2", -1.5e-5, 3.9e-4, 7.9e-4, 4.3e-3),
]
TABLE_4_7_COLUMNS = ("sim1", "sim2", "sim3", "experiment")
ROD_ERROR = 0.02  # m: rod 26 made 20 mm longer (seed 004 §4.4.1), the "perturbed model" of Table 4.7


def thesis_perturbed(robot):
    """Table 4.7 column 3: the nominal model with rod 26 (j26.d1) 20 mm longer."""
    return robot.nominal.at[robot.index("j26.d1")].add(ROD_ERROR)


def thesis_identified(robot, column: str):
    """The thesis' identified model of one Table 4.7 column ("sim1", "sim2", "sim3", "experiment"):
    perturbed model + the printed identified - perturbed differences (2 significant digits)."""
    k = 1 + TABLE_4_7_COLUMNS.index(column)
    a = np.array(thesis_perturbed(robot))
    for row in TABLE_4_7:
        a[robot.index(row[0])] += row[k]
    return jnp.asarray(a)
