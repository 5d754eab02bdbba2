"""Self-calibration from joint readings only (seed 000 §7.4): pointing tool with two targets at a
known distance (eq 7.9-7.12), and the pose-target variant. Both are calibrations through the one core
(`jaxcal.fit.core`): a `Problem` with a device whose parameters are the unknown targets, solved by
`core.calibrate` / `core.solve`.

Pointer (`jaxcal.measure.aim_line`): a pointer on the tool, leaving the tool frame at `offset` along
`direction` (tool frame; default the tool z axis from the tool origin), is aimed at target i from
configurations q_ik. It is a virtual prismatic joint of unknown extension lambda_ik whose tip is the
target (eq 7.10): o(q_ik) + lambda_ik u(q_ik) = p_i. Only joint readings are recorded; the targets'
positions are unknown but their distance d is known (eq 7.9, 7.11). Eq 7.12 is solved with lambda
eliminated (each aim says: the perpendicular offset (I - u u^T)(p_i - o) is zero) and the targets
p_1, p_2 estimated with the robot, plus one sample saying |p_1 - p_2| = d.

The aims determine the targets only when the aim lines at each target are not all parallel. On the
thesis' MRR-1 (R-R-P, all joint axes vertical) the tool z axis always points straight down: every aim
line is vertical, a target's height is invisible to its aims and the distance constrains only the
difference of the two heights. `calibrate` checks this before solving: every target coordinate must be
in the base set (QR, seed 001 App. III, threshold core.BASE_TOL) and the Jacobian's rank by SVD under
the same relative threshold must equal the base-set count; otherwise it raises `SelfCalibrationError`
(or warns, `strict=False`).

`residual` keeps the closed-form elimination of the targets (each p_i the least-squares intersection of
its aim lines) for the GA (`identify_ga`, a search over the robot parameters only) and for checks; it
is singular for parallel aim lines, which is why the core path estimates the targets explicitly.

Pose-target variant (the end of §7.4, `jaxcal.measure.pose_target`): M full-pose targets (e.g.
three-point targets) on a fixture whose poses X_i relative to each other were established in advance;
the fixture's pose W is unknown. The end-effector is matched to target i at joint readings q_i:
F(q_i, a) = W X_i, i.e. the reading W^-1 F(q_i) is X_i; W is a device frame estimated with the robot
(`pose_target_residual` keeps the formulation with W eliminated relative to the first target, for the GA).
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal.fit import core
from jaxcal.fit.base import numerical_rank
from jaxcal.forward import forward
from jaxcal.kin.rotations import log_so3
from jaxcal.measure.registry import make_device

Z_AXIS = (0.0, 0.0, 1.0)
ORIGIN = (0.0, 0.0, 0.0)
# Solver settings of the self-calibration solves: noise-free aims are solved to round-off.
SETTINGS = core.Settings(rtol=1e-12, atol=1e-15)


class SelfCalibrationError(ValueError):
    """The aims (or pose targets) cannot determine the targets or the parameters."""


def _lines(robot, a, q, direction=Z_AXIS, offset=ORIGIN):
    """Origins (K, 3) and unit directions (K, 3) of the aim lines at joint values q (K, n)."""
    tip = forward(robot, a, q)
    u = jnp.asarray(direction) / jnp.linalg.norm(jnp.asarray(direction))
    return tip.p + tip.R @ jnp.asarray(offset), tip.R @ u


def nearest_point(o, u):
    """Least-squares intersection of lines o_k + t u_k: solve sum(I - u u^T) p = sum(I - u u^T) o
    (singular when all u are parallel)."""
    P = jnp.eye(3) - u[:, :, None] * u[:, None, :]
    return jnp.linalg.solve(P.sum(0), jnp.einsum("kij,kj->i", P, o))


def residual(robot, a, q1, q2, d, w_d=1.0, direction=Z_AXIS, offset=ORIGIN):
    """Eq 7.12 with the targets eliminated in closed form, for aims q1 at target 1 and q2 at target 2:
    each aim line's offset from its target's nearest point, then w_d (|p_1 - p_2| - d)."""
    o1, u1 = _lines(robot, a, q1, direction, offset)
    o2, u2 = _lines(robot, a, q2, direction, offset)
    p1, p2 = nearest_point(o1, u1), nearest_point(o2, u2)

    def off_line(p, o, u):
        v = p - o
        return v - jnp.sum(v * u, -1, keepdims=True) * u

    dist = jnp.linalg.norm(p1 - p2) - d
    return jnp.concatenate([off_line(p1, o1, u1).reshape(-1), off_line(p2, o2, u2).reshape(-1), w_d * dist[None]])


def pose_target_residual(robot, a, q, X):
    """Pose-target residual with W eliminated: q (M, n) joint readings matching targets with fixture
    poses X (M, 4, 4); 6 (M - 1) entries: F(q_0)^-1 F(q_i) against X_0^-1 X_i (position, rotation vector)."""
    tip = forward(robot, a, q)
    X = jnp.asarray(X)
    R0, p0 = tip.R[0], tip.p[0]
    XR0, Xp0 = X[0, :3, :3], X[0, :3, 3]
    rel_p = (tip.p[1:] - p0) @ R0                       # R_0^T (p_i - p_0), rows
    rel_R = jnp.einsum("ji,njk->nik", R0, tip.R[1:])     # R_0^T R_i
    want_p = (X[1:, :3, 3] - Xp0) @ XR0
    want_R = jnp.einsum("ji,njk->nik", XR0, X[1:, :3, :3])
    rot = jax.vmap(log_so3)(jnp.einsum("nji,njk->nik", want_R, rel_R))
    return jnp.concatenate([rel_p - want_p, rot], axis=1).reshape(-1)


# -- the problems -------------------------------------------------------------------------------------
def _robot_free(robot, free_idx):
    free = np.zeros(robot.n_params, bool)
    free[np.flatnonzero(robot.free_mask) if free_idx is None else np.asarray(free_idx, int)] = True
    return free


def aim_problem(robot, aims, distances, *, direction=Z_AXIS, offset=ORIGIN, a0=None, free_idx=None, sigma=1.0,
                sigma_distance=None) -> core.Problem:
    """The core `Problem` of pointer self-calibration (eq 7.9-7.12).

    aims: one array (K_i, n_inputs) of joint readings per target; distances: {(i, j): d_ij} (0-based) or
    one number d for two targets; direction / offset: the pointer in the tool frame; a0: robot start
    (default nominal); free_idx: robot indices that may be estimated (default the robot's free mask);
    sigma / sigma_distance: standard deviations of the aim offsets and of the distances (weights 1/sigma).
    The targets start at the least-squares intersection of their aim lines at a0 and are all free; where the
    lines are parallel, the point nearest the lines' mean origin (not the robot base, whose height would put
    every target at one level, where the distances give no gradient along the lines)."""
    device = make_device("aim_line", targets=len(aims), direction=direction, offset=offset)
    if np.ndim(distances) == 0 and not isinstance(distances, dict):
        distances = {(0, 1): float(distances)}
    a0 = np.asarray(robot.nominal_np if a0 is None else a0, float)
    starts = []
    for Q in aims:
        o, u = (np.asarray(v) for v in _lines(robot, jnp.asarray(a0), jnp.asarray(Q), device.direction, device.offset))
        P = np.eye(3) - u[:, :, None] * u[:, None, :]
        c = o.mean(0)
        starts.append(c + np.linalg.lstsq(P.sum(0), np.einsum("kij,kj->i", P, o - c), rcond=None)[0])
    q = np.concatenate([np.asarray(Q, float) for Q in aims] + [np.asarray(aims[0], float)[:1]])
    y = np.stack([device.aim_reading(i) for i, Q in enumerate(aims) for _ in range(len(Q))]
                 + [device.distance_reading(distances)])
    w = np.full(device.reading_shape, 1.0 / sigma)
    w[3 * len(aims):] = 1.0 / (sigma if sigma_distance is None else sigma_distance)
    free = np.concatenate([_robot_free(robot, free_idx), np.ones(device.n_params, bool)])
    return core.make_problem(robot, device, q, y, weights=w, free=free, a_ref=np.concatenate([a0, np.concatenate(starts)]))


def pose_target_problem(robot, q, X, *, a0=None, free_idx=None) -> core.Problem:
    """The core `Problem` of pose-target self-calibration: readings X (M, 4, 4) at joint readings q (M, n),
    fixture frame W unknown (the core's start registers it), unit weights (m, rad) as in the elimination form."""
    device = make_device("pose_target")
    a0 = np.asarray(robot.nominal_np if a0 is None else a0, float)
    free = np.concatenate([_robot_free(robot, free_idx), np.ones(device.n_params, bool)])
    return core.make_problem(robot, device, q, X, weights=np.ones(6), free=free,
                             a_ref=np.concatenate([a0, np.asarray(device.nominal_np)]))


# -- what the data determine ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Determinacy:
    """What the aims determine at the start x (robot at the prior, targets fitted).

    estimated: robot indices of the base set; device_estimated / device_undetermined: device parameter
    names in / out of the base set; base_count: QR base-set size (robot and device); rank: SVD rank of the
    free columns under the same threshold; robot_rank: rank - rank of the device columns (the rank left
    for the robot once the targets are eliminated); singular: singular values of the free columns."""

    estimated: np.ndarray
    device_estimated: tuple
    device_undetermined: tuple
    base_count: int
    rank: int
    robot_rank: int
    singular: np.ndarray
    x: np.ndarray

    @property
    def problems(self) -> list[str]:
        """Why the data cannot determine the parameters (empty when they can)."""
        out = []
        if self.device_undetermined:
            out.append(f"the target parameter(s) {list(self.device_undetermined)} are not determined by the data "
                       "(aim lines at a target all parallel, or too few aims)")
        if self.rank != self.base_count:
            out.append(f"the Jacobian's SVD rank {self.rank} differs from the QR base-set count {self.base_count} "
                       "(ill-conditioned: no gap in the spectrum at the threshold)")
        if not self.estimated.size:
            out.append("no robot parameter is identifiable")
        return out


def determinacy(problem: core.Problem, x, base_tol: float | None = None) -> Determinacy:
    """Base set and SVD rank of the free columns of the weighted Jacobian at x, under one relative threshold
    (base_tol, default core.BASE_TOL): QR pivots (seed 001 eq 34) and singular values both compared with
    base_tol times the largest."""
    nr = problem.robot.n_params
    J = core.jacobian(problem.robot, problem.device, x, problem.q, problem.y, problem.w)
    est, _, _, _ = core.choose_estimated(problem, J, True, base_tol)
    c = (core.BASE_TOL if base_tol is None else base_tol) / np.finfo(float).eps
    free = np.flatnonzero(problem.free)
    dev_free = free[free >= nr]
    rank = numerical_rank(J[:, free], c)
    names = problem.names
    return Determinacy(
        estimated=est[est < nr], device_estimated=tuple(names[i] for i in est[est >= nr]),
        device_undetermined=tuple(names[i] for i in sorted(set(dev_free) - set(est))), base_count=len(est), rank=rank,
        robot_rank=rank - numerical_rank(J[:, dev_free], c), singular=np.linalg.svd(J[:, free], compute_uv=False),
        x=np.asarray(x))


def start_determinacy(problem: core.Problem, settings: core.Settings = SETTINGS, base_tol=None) -> Determinacy:
    """`determinacy` at the core's start (robot at its prior, device parameters fitted)."""
    x, _, _ = core.start(problem, settings)
    return determinacy(problem, x, base_tol)


def identifiable(robot, a, q1, q2, d, free_idx=None, direction=Z_AXIS, offset=ORIGIN, base_tol=None) -> Determinacy:
    """What the two-target aims q1, q2 at distance d determine at robot parameters a (targets fitted)."""
    return start_determinacy(aim_problem(robot, [q1, q2], d, direction=direction, offset=offset, a0=a,
                                         free_idx=free_idx), base_tol=base_tol)


def pose_target_identifiable(robot, a, q, X, free_idx=None, base_tol=None) -> Determinacy:
    """What the pose targets X at joint readings q determine at robot parameters a (fixture frame fitted)."""
    return start_determinacy(pose_target_problem(robot, q, X, a0=a, free_idx=free_idx), base_tol=base_tol)


# -- calibration through the core ------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SelfCalibration:
    """a: robot parameters; device_params: the targets (or fixture frame); converged; determinacy: the
    check made before solving; calibration: the core's result (None when `estimated` was given: one
    core.solve); solution: the core's solver run of the final stage (None for core.calibrate)."""

    a: np.ndarray
    device_params: np.ndarray
    converged: bool
    determinacy: Determinacy
    calibration: core.Calibration | None
    solution: core.Solution | None


def calibrate_problem(problem: core.Problem, settings: core.Settings = SETTINGS, *, estimated=None, strict=True,
                      base_tol=None) -> SelfCalibration:
    """Check what the data determine, then calibrate through the core.

    estimated: robot indices to estimate (the device parameters are always estimated): one core.solve from
    the core's start; None: core.calibrate (its base set). strict: raise SelfCalibrationError when the data
    cannot determine the parameters (`Determinacy.problems`), else warn and solve anyway."""
    det = start_determinacy(problem, settings, base_tol)
    if det.problems:
        msg = f"{problem.robot.name} self-calibration ({problem.device.kind}): " + "; ".join(det.problems)
        if strict:
            raise SelfCalibrationError(msg)
        warnings.warn(msg, stacklevel=3)
    nr = problem.robot.n_params
    if estimated is None:
        cal = core.calibrate(problem, settings, base_tol=base_tol)
        return SelfCalibration(cal.x[:nr], cal.x[nr:], cal.converged and cal.frames_converged, det, cal, None)
    dev_idx = np.flatnonzero(problem.free[nr:]) + nr
    sol = core.solve(problem, det.x, np.concatenate([np.asarray(estimated, int), dev_idx]), settings)
    return SelfCalibration(sol.x[:nr], sol.x[nr:], sol.converged, det, None, sol)


def calibrate(robot, aims, distances, *, direction=Z_AXIS, offset=ORIGIN, a0=None, free_idx=None, estimated=None,
              settings: core.Settings = SETTINGS, strict=True, base_tol=None) -> SelfCalibration:
    """Pointer self-calibration (eq 7.9-7.12) through the core; see `aim_problem` and `calibrate_problem`."""
    problem = aim_problem(robot, aims, distances, direction=direction, offset=offset, a0=a0, free_idx=free_idx)
    return calibrate_problem(problem, settings, estimated=estimated, strict=strict, base_tol=base_tol)


def calibrate_pose_targets(robot, q, X, *, a0=None, free_idx=None, estimated=None, settings: core.Settings = SETTINGS,
                           strict=True, base_tol=None) -> SelfCalibration:
    """Pose-target self-calibration through the core; see `pose_target_problem` and `calibrate_problem`."""
    problem = pose_target_problem(robot, q, X, a0=a0, free_idx=free_idx)
    return calibrate_problem(problem, settings, estimated=estimated, strict=strict, base_tol=base_tol)


def identify_lm(robot, q1, q2, d, est_idx, a0=None, direction=Z_AXIS, offset=ORIGIN, strict=True):
    """LM (the core's solver) on the robot parameters est_idx and the two targets, others pinned at a0.
    Returns (a, converged)."""
    sc = calibrate(robot, [q1, q2], d, direction=direction, offset=offset, a0=a0, estimated=est_idx, strict=strict)
    return sc.a, sc.converged


def identify_pose_target_lm(robot, q, X, est_idx, a0=None, strict=True):
    """LM (the core's solver) on the robot parameters est_idx and the fixture frame, others pinned at a0.
    Returns (a, converged)."""
    sc = calibrate_pose_targets(robot, q, X, a0=a0, estimated=est_idx, strict=strict)
    return sc.a, sc.converged


# -- joint values for the aims (inverse kinematics: solves for q, not for parameters) -------------------------
def aim_configurations(robot, a, target, q_starts, direction=Z_AXIS, offset=ORIGIN):
    """Joint values aiming the pointer (direction, offset in the tool frame) at `target` (IK by LM from
    each start, vmapped); returns (q (K, n), off-line distance (K,)) so the caller can keep the converged ones."""
    def fn(q, _):
        o, u = _lines(robot, a, q[None], direction, offset)
        o, u = o[0], u[0]
        v = target - o
        return v - jnp.dot(v, u) * u

    def one(q0):
        sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-13, atol=1e-15), q0, None, max_steps=200, throw=False)
        return sol.value, jnp.linalg.norm(fn(sol.value, None))

    return jax.jit(jax.vmap(one))(jnp.asarray(q_starts))


def _identify_ga(residual_fn, robot, args, est_idx, population, generations, bound, seed, a0, options):
    """The GA (jaxcal.ga.core) on residual_fn: cost = sum of squares, variables dg on est_idx (a search,
    not a least-squares solve: the closed-form residual with the targets eliminated)."""
    from jaxcal.ga import core as ga_core

    a0 = robot.nominal if a0 is None else jnp.asarray(a0)
    idx = jnp.asarray(est_idx)
    opts = ga_core.GAOptions(population=population, generations=generations, **options)

    def fitness_of(dg, data):
        return jnp.sum(residual_fn(robot, data["a0"].at[idx].add(dg), *data["args"]) ** 2)

    payload = dict(a0=a0, args=args)
    lb, ub = -bound * jnp.ones(len(est_idx)), bound * jnp.ones(len(est_idx))
    _, init_random = ga_core.make_init_fn(fitness_of, opts)
    state = init_random(jax.random.split(jax.random.PRNGKey(seed), 1), payload, lb, ub)
    state, best, _ = ga_core.make_chunk_fn(fitness_of, opts, generations)(state, payload, lb, ub)
    dg, _ = jax.vmap(ga_core.best_individual)(state)
    return a0.at[idx].add(dg[0]), np.asarray(best[0])


def identify_ga(robot, q1, q2, d, est_idx, *, population=50, generations=250, bound=0.005, seed=0, a0=None,
                direction=Z_AXIS, offset=ORIGIN, **options):
    """The GA on the two-target residual (pointer direction, offset in the tool frame). Returns (a, best
    cost per generation)."""
    args = (jnp.asarray(q1), jnp.asarray(q2), jnp.float64(d), 1.0, tuple(direction), tuple(offset))
    return _identify_ga(residual, robot, args, est_idx, population, generations, bound, seed, a0, options)


def identify_pose_target_ga(robot, q, X, est_idx, *, population=50, generations=250, bound=0.005, seed=0, a0=None,
                            **options):
    """The GA on the pose-target residual. Returns (a, best cost per generation)."""
    args = (jnp.asarray(q), jnp.asarray(X))
    return _identify_ga(pose_target_residual, robot, args, est_idx, population, generations, bound, seed, a0, options)


def pose_configurations(robot, a, X, q_starts):  # IK: solves for joint values
    """Joint values matching the tool frame to the poses X (M, 4, 4) (IK by LM from q_starts (M, n),
    vmapped); returns (q (M, n), pose residual norm (M,))."""
    def fn(q, target):
        tip = forward(robot, a, q)
        return jnp.concatenate([tip.p - target[:3, 3], log_so3(target[:3, :3].T @ tip.R)])

    def one(q0, target):
        sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-13, atol=1e-15), q0, target, max_steps=200,
                                 throw=False)
        return sol.value, jnp.linalg.norm(fn(sol.value, target))

    return jax.jit(jax.vmap(one))(jnp.asarray(q_starts), jnp.asarray(X))
