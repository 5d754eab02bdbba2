"""GECARO's nine calibration methods (seed 001 §3) as residuals, with point generation.

Each method is a residual of one sample r(a, c, q_i, q_j): a is the robot parameter vector,
c the method's own unknowns (plane coefficients; empty for the others) and (q_i, q_j) a pair
of configurations (single-configuration methods ignore q_j). The tool point/frame is the
origin of frame n+1 in the world frame -1 (no separate device frame: GECARO's base
parameters theta0, r0 play that role).

| method          | equation | residual of one sample                         | unknowns c |
|-----------------|----------|------------------------------------------------|------------|
| position        | [7] 1-3  | P(q) - P_meas                                  |            |
| location        | [7]      | (P(q) - P_meas, log(R_meas R(q)^T))            |            |
| point_link      | [12] 1-3 | P(q_i) - P(q_j)                                |            |
| frame_link      | [12]     | (P(q_i) - P(q_j), log(R(q_i) R(q_j)^T))        |            |
| plane1_known    | [14]     | (c . P(q) + 1) / |c|                           | known      |
| plane1_unknown  | [14-15]  | same, c identified                             | a, b, c    |
| plane2_known    | [16-17]  | n . (P(q_i) - P(q_j))                          | known      |
| plane2_unknown  | [16-17]  | same, n identified                             | a, b, c    |
| distance        | [18-20]  | |P(q_i) - P(q_j)| - D_meas                     |            |

Point generation (§4 "Points generation") makes configurations that satisfy each constraint
to machine precision: random configurations, and a numerical inverse kinematics (damped
Gauss-Newton in the row space of the task Jacobian, vmapped over starts) for the link
methods (same point/frame on another branch) and the plane methods (points on a plane).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.forward import forward
from jaxcal.kin.model import Robot
from jaxcal.kin.rotations import log_so3

METHODS = ("position", "location", "point_link", "frame_link", "plane1_known", "plane1_unknown",
           "plane2_known", "plane2_unknown", "distance")
PAIR_METHODS = ("point_link", "frame_link", "plane2_known", "plane2_unknown", "distance")
PLANE_METHODS = ("plane1_known", "plane1_unknown", "plane2_known", "plane2_unknown")


def check_method(method: str) -> str:
    if method not in METHODS:
        raise ValueError(f"unknown calibration method {method!r}; expected one of {METHODS}")
    return method


def n_rows(method: str) -> int:
    """Residual components per sample."""
    return {"position": 3, "location": 6, "point_link": 3, "frame_link": 6}.get(method, 1)


def extra_names(method: str) -> tuple[str, ...]:
    """Names of the method's own unknowns (identified with the robot, not counted as robot parameters)."""
    return ("plane.a", "plane.b", "plane.c") if method in ("plane1_unknown", "plane2_unknown") else ()


def _tool(robot, a, q):
    pose = forward(robot, a, q)
    return pose.R, pose.p


def sample_residual(robot: Robot, method: str, a, c, qi, qj, y):
    """Residual of one sample (seed 001 eq 7, 12, 14, 16, 18). y: the sample's measurement
    (position (3,), location (4, 4), distance ()); c: plane coefficients for plane methods."""
    Ri, pi = _tool(robot, a, qi)
    if method == "position":
        return pi - y
    if method == "location":
        return jnp.concatenate([pi - y[:3, 3], log_so3(y[:3, :3] @ Ri.T)])
    if method == "plane1_known" or method == "plane1_unknown":
        return jnp.atleast_1d((c @ pi + 1.0) / jnp.linalg.norm(c))
    Rj, pj = _tool(robot, a, qj)
    if method == "point_link":
        return pi - pj
    if method == "frame_link":
        return jnp.concatenate([pi - pj, log_so3(Ri @ Rj.T)])
    if method == "plane2_known" or method == "plane2_unknown":
        return jnp.atleast_1d(c @ (pi - pj) / jnp.linalg.norm(c))
    if method == "distance":
        return jnp.atleast_1d(jnp.linalg.norm(pi - pj) - y)
    raise ValueError(f"unknown calibration method {method!r}")


@functools.partial(jax.jit, static_argnums=(0, 1))
def stacked_residual(robot: Robot, method: str, a, c, Qi, Qj, Y):
    """All samples' residuals, flattened (N * n_rows(method),)."""
    f = lambda qi, qj, y: sample_residual(robot, method, a, c, qi, qj, y)  # noqa: E731
    return jax.vmap(f)(Qi, Qj, Y).reshape(-1)


@functools.partial(jax.jit, static_argnums=(0, 1))
def observation_matrix(robot: Robot, method: str, a, c, Qi, Qj, Y):
    """W = d r / d (a, c) by forward-mode autodiff (columns: robot parameters then c)."""
    x = jnp.concatenate([a, c])
    n = a.shape[0]
    return jax.jacfwd(lambda x: stacked_residual(robot, method, x[:n], x[n:], Qi, Qj, Y))(x)


# -- numerical inverse kinematics ------------------------------------------------------------
def _task(robot, kind, a, target, q):
    """Task residual: 'point' (3), 'frame' (6) or 'plane' (1, target = plane coefficients)."""
    R, p = _tool(robot, a, q)
    if kind == "point":
        return p - target[:3]
    if kind == "frame":
        Rt = target[3:].reshape(3, 3)
        return jnp.concatenate([p - target[:3], log_so3(Rt @ R.T)])
    return jnp.atleast_1d((target[:3] @ p + 1.0) / jnp.linalg.norm(target[:3]))


@functools.partial(jax.jit, static_argnames=("robot", "kind", "steps"))
def solve_ik(robot: Robot, kind: str, a, target, q0, steps: int = 60):
    """Levenberg-Marquardt in the row space: dq = -J^T (J J^T + lam I)^-1 r, lam adapted.

    Works for square (frame), under-determined (point, plane) tasks and converges to
    ~1e-16 residual. Returns (q, |r|)."""
    fn = lambda q: _task(robot, kind, a, target, q)  # noqa: E731

    def body(state, _):
        q, lam = state
        r = fn(q)
        J = jax.jacfwd(fn)(q)
        dq = -J.T @ jnp.linalg.solve(J @ J.T + lam * jnp.eye(r.shape[0]), r)
        q_new = q + dq
        better = jnp.linalg.norm(fn(q_new)) < jnp.linalg.norm(r)
        return (jnp.where(better, q_new, q), jnp.where(better, lam * 0.3, lam * 10.0)), None

    (q, _), _ = jax.lax.scan(body, (q0, jnp.float64(1e-3)), None, length=steps)
    return q, jnp.linalg.norm(fn(q))


def _solve_ik_many(robot, kind, a, targets, Q0):
    return jax.vmap(lambda t, q0: solve_ik(robot, kind, a, t, q0))(targets, Q0)


def _random_q(robot, n, rng, margin=0.1):
    lo, hi = robot.q_min + margin, robot.q_max - margin
    return lo + (hi - lo) * rng.uniform(size=(n, robot.n_inputs))


def _within(robot, Q):
    return np.all((Q >= robot.q_min) & (Q <= robot.q_max), axis=-1)


def default_plane(robot: Robot, a=None):
    """A tilted plane (not normal to the first joint axis) through the tool point at home:
    coefficients (a, b, c) of a x + b y + c z + 1 = 0 (seed 001 eq 13)."""
    a = robot.nominal if a is None else a
    p0 = np.asarray(forward(robot, a, jnp.asarray(robot.home)).p)
    n = np.array([0.3, 0.4, 0.866])
    n /= np.linalg.norm(n)
    return -n / (n @ p0)


@dataclasses.dataclass(frozen=True)
class Points:
    """Generated configurations for one method: Qi, Qj (= Qi for single-configuration methods),
    the exact measurements Y at parameters a, and the plane (if any); `constraint` is the largest
    constraint violation (m or rad)."""

    method: str
    Qi: np.ndarray
    Qj: np.ndarray
    Y: np.ndarray
    plane: np.ndarray
    constraint: float


def _link_partners(robot, a, kind, Qi, rng, n_starts, arm_joints):
    """For each q_i a q_j on another branch reaching the same point/frame (seed 001 §3.2):
    IK from n_starts random starts; keep the solution whose arm joints differ most."""
    N = len(Qi)
    R, p = _tool(robot, a, jnp.asarray(Qi))
    targets = np.concatenate([np.asarray(p), np.asarray(R).reshape(N, 9)], axis=1)
    starts = _random_q(robot, N * n_starts, rng, margin=0.0)
    tgt = np.repeat(targets, n_starts, axis=0)
    Qs, err = _solve_ik_many(robot, kind, a, jnp.asarray(tgt), jnp.asarray(starts))
    Qs, err = np.asarray(Qs).reshape(N, n_starts, -1), np.asarray(err).reshape(N, n_starts)
    dist = np.linalg.norm((Qs - Qi[:, None])[..., arm_joints], axis=-1)
    ok = (err < 1e-12) & _within(robot, Qs)
    score = np.where(ok, dist, -np.inf)
    best = np.argmax(score, axis=1)
    found = np.take_along_axis(score, best[:, None], 1)[:, 0] > 1e-3
    return Qs[np.arange(N), best], err[np.arange(N), best], found


def generate_points(robot: Robot, method: str, n: int, seed: int = 0, a=None, plane=None,
                    n_starts: int = 24, arm_joints=(0, 1, 2)) -> Points:
    """n samples satisfying the method's constraint at parameters a (default nominal).

    Link methods: pairs on different branches (frame link: the arm joints `arm_joints` change,
    not only the wrist). Plane methods: tool points on `plane` (default `default_plane`).
    Distance: random pairs with their exact distance."""
    check_method(method)
    a = robot.nominal if a is None else jnp.asarray(a, dtype=jnp.float64)
    rng = np.random.default_rng(seed)
    plane = np.asarray(default_plane(robot, a) if plane is None else plane, float)
    arm = np.asarray(arm_joints)
    if method in ("point_link", "frame_link"):
        kind = "point" if method == "point_link" else "frame"
        Qi_all, Qj_all = [], []
        while sum(len(x) for x in Qi_all) < n:
            Qi = _random_q(robot, 2 * n, rng)
            Qj, _, found = _link_partners(robot, a, kind, Qi, rng, n_starts, arm if kind == "frame" else slice(None))
            Qi_all.append(Qi[found])
            Qj_all.append(Qj[found])
        Qi, Qj = np.concatenate(Qi_all)[:n], np.concatenate(Qj_all)[:n]
    elif method in PLANE_METHODS:
        m = n if method.startswith("plane1") else 2 * n
        pts = []
        while sum(len(x) for x in pts) < m:
            Q0 = _random_q(robot, 2 * m, rng)
            tgt = np.tile(np.concatenate([plane, np.zeros(9)]), (len(Q0), 1))
            Qs, err = _solve_ik_many(robot, "plane", a, jnp.asarray(tgt), jnp.asarray(Q0))
            Qs, err = np.asarray(Qs), np.asarray(err)
            pts.append(Qs[(err < 1e-14) & _within(robot, Qs)])
        P = np.concatenate(pts)[:m]
        Qi, Qj = (P, P) if method.startswith("plane1") else (P[0::2], P[1::2])
    else:
        Qi = _random_q(robot, n, rng)
        Qj = _random_q(robot, n, rng) if method == "distance" else Qi
    Y = exact_measurements(robot, method, a, Qi, Qj)
    c = jnp.asarray(plane if method in PLANE_METHODS else np.zeros(0))
    viol = np.asarray(stacked_residual(robot, method, a, c, jnp.asarray(Qi), jnp.asarray(Qj), jnp.asarray(Y)))
    return Points(method, Qi, Qj, Y, plane if method in PLANE_METHODS else np.zeros(0), float(np.max(np.abs(viol))))


def exact_measurements(robot: Robot, method: str, a, Qi, Qj):
    """Noise-free measurements at parameters a: position (N, 3), location (N, 4, 4), distance
    (N,); zeros (N,) for the methods without a measurement (links, planes)."""
    R, p = _tool(robot, a, jnp.asarray(Qi))
    if method == "position":
        return np.asarray(p)
    if method == "location":
        T = np.zeros((len(Qi), 4, 4))
        T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = np.asarray(R), np.asarray(p), 1.0
        return T
    if method == "distance":
        pj = np.asarray(_tool(robot, a, jnp.asarray(Qj))[1])
        return np.linalg.norm(np.asarray(p) - pj, axis=1)
    return np.zeros(len(Qi))


def nearest_plane(P) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares plane through points P (N, 3): (centroid, unit normal).

    The normal is the right singular vector of the centred points with the smallest singular
    value, so the plane minimises the sum of squared orthogonal distances."""
    P = np.asarray(P, float).reshape(-1, 3)
    if len(P) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(P)}")
    centroid = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - centroid, full_matrices=False)
    if s[1] <= 1e-12 * max(s[0], 1e-300):
        raise ValueError("the points are collinear: no unique nearest plane")
    return centroid, vt[-1]


def plane_coefficients(centroid, normal) -> np.ndarray:
    """(a, b, c) of a x + b y + c z + 1 = 0 (seed 001 eq 13) for the plane through `centroid`
    with `normal`; eq 13 cannot hold a plane through the world origin."""
    offset = float(np.dot(normal, centroid))
    if abs(offset) < 1e-9:
        raise ValueError("the plane passes through the world origin: eq 13 (a x + b y + c z + 1 = 0) cannot express it")
    return -np.asarray(normal, float) / offset


def initial_plane(robot: Robot, method: str, a, Qi, Qj) -> np.ndarray:
    """Start of an unknown plane (seed 001 §3.3.1): the nearest plane to the tool points that the
    model at parameters a (the nominal robot) gives for the joint readings (both configurations of
    each pair for plane2_unknown). Returned as the coefficients (a, b, c) of eq 13 for both methods,
    as `Points.plane` holds a plane; for eq 16 only their direction, the plane's normal, counts."""
    if method not in ("plane1_unknown", "plane2_unknown"):
        raise ValueError(f"{method!r} has no unknown plane")
    Q = jnp.asarray(Qi) if method == "plane1_unknown" else jnp.concatenate([jnp.asarray(Qi), jnp.asarray(Qj)])
    return plane_coefficients(*nearest_plane(np.asarray(_tool(robot, jnp.asarray(a), Q)[1])))


def method_unknowns(method: str, plane) -> np.ndarray:
    """Initial/known values of the method's own unknowns c (the plane coefficients or normal)."""
    return np.asarray(plane, float) if method in PLANE_METHODS else np.zeros(0)
