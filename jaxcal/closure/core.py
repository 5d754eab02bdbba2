"""Loop closure of trees with closure pairs (seed 004 §2.3-2.4).

A closed mechanism is described as an open tree (bodies of any joint convention, e.g. MCPC rows or
the planar absolute-angle bodies built by `jaxcal.closure.planar`) plus a `Closure`: which body
frames must coincide (closure pairs), which non-actuated joints are free, and the free-joint start
that selects the assembly mode.

Closure (seed 004 eq 2.19-2.25): with g_p = [r_0p; eta_p] the position and Euler parameters of
frame p, find theta_free minimising sum_i v_i^T Wc v_i with v_i = g_{p_i} - g_{q_i}; at a spherical
closure only the position rows are kept. The minimiser is optimistix's Levenberg-Marquardt; its
derivative is the implicit function theorem written as a `jax.custom_jvp` (Gauss-Newton form, exact
at v = 0), so `jax.jacfwd` of `forward_closed` with respect to `a` is the closed-loop Jacobian of
eq 2.65/2.69. (optimistix's own `ImplicitAdjoint` gives the same numbers but differentiates the
Hessian of |v|^2: compiling jacfwd through it took ~36 s for the 3-D four-bar against ~4 s here.)

Robustness: the default solver ("track") follows the closed configuration by continuation from the
nominal closed configuration (`jaxcal.closure.track`): a sample either closes on that branch or is
reported (status UNCLOSED, or OTHER_MODE when it closes only in another assembly mode).

Failure is data: the thesis' check (|v| > 1e-10 after convergence) flags a sample; `solve` returns
the flag and `forward_closed` moves a flagged sample's position by `FAIL_OFFSET` metres and turns
its frame by `FAIL_ROTATION` (finite, no NaN, but far from any reading of any device kind) so a fit
step that makes a sample infeasible raises the cost and is rejected by the line search / trust
region, as the thesis returns Inf (§3.3).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal import exported
from jaxcal.autodiff import value_and_jacfwd
from jaxcal.closure.track import CLOSED, OTHER_MODE, UNCLOSED, Tracked, corrector, damped_newton, track
from jaxcal.kin.model import Robot, frames_single, joint_variables, map_leading_axes
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import quat_from_matrix
from jaxcal.linalg import solve_small
from jaxcal.loops import varying_with

CLOSURE_KINDS = ("full", "position")
SOLVERS = ("track", "lm", "newton")
FAIL_OFFSET = 1.0e3  # metres added to each coordinate of a sample whose loops do not close
# rotation applied to the tool of a sample whose loops do not close: the cyclic permutation x -> y -> z -> x
# (120 degrees about (1, 1, 1)), so every axis an orientation device reads moves by 90 degrees
FAIL_ROTATION = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
CLOSED_TOL = 1e-10  # seed 004 §2.4.1: residual norm above this is a failure to close


@dataclasses.dataclass(frozen=True)
class Closure:
    """How a tree is closed. Bodies are numbered 1..N as in the seed's Table 4.1.

    pairs: (p, q, kind) closure pairs; kind "full" matches position and Euler parameters (rotary and
        prismatic closures), "position" matches position only (spherical closures, eq 2.23).
    free: bodies whose joint variable is solved by closure, in the order of theta_free.
    start: default theta_free start (selects the assembly mode).
    w_position, w_orientation: diagonal of the weighting matrix Wc (eq 2.25).
    start_fn: optional start_fn(a, qj) -> theta_free start per sample (e.g. a nominal direct
        solution, seed §2.4); used instead of `start` when given (no derivative flows through it).
    solver: "track" (the default: continuation from the nominal closed configuration,
        `jaxcal.closure.track`, which cannot switch assembly mode silently), "lm" (optimistix
        Levenberg-Marquardt from the start) or "newton" (the Newton/LM hybrid `newton_lm`). The two
        direct solvers fall back to the continuation for samples they do not close, but a sample they
        close is not checked against the nominal branch.
    """

    pairs: tuple[tuple[int, int, str], ...]
    free: tuple[int, ...]
    start: tuple[float, ...]
    w_position: float = 1.0
    w_orientation: float = 1.0
    tol: float = CLOSED_TOL
    max_steps: int = 100
    solver: str = "track"
    start_fn: Callable | None = None

    def serving(self, robot: Robot, a, free_mask=None) -> Robot:
        """The robot whose closure serves parameters a (and, in a fit, any change of the entries free_mask
        frees): the robot itself. A mechanism-specific closure whose shortcut holds only for some fixed
        entries (the Delta's) answers with the generic closure where they are off or free."""
        return robot

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"closure solver must be one of {SOLVERS}, got {self.solver!r}")
        for k, (p, q, kind) in enumerate(self.pairs):
            if kind not in CLOSURE_KINDS:
                raise ValueError(f"closure pair {k} ({p}, {q}): kind must be one of {CLOSURE_KINDS}, got {kind!r}")
            if p == q or p < 1 or q < 1:
                raise ValueError(f"closure pair {k}: bodies must be two different body numbers >= 1, got ({p}, {q})")
        if len(self.start) != len(self.free):
            raise ValueError(f"closure start has {len(self.start)} values for {len(self.free)} free joints")
        if len(set(self.free)) != len(self.free):
            raise ValueError(f"closure free joints repeat a body: {self.free}")

    @property
    def n_free(self) -> int:
        return len(self.free)

    # whether reverse-mode derivatives (J^T, needed by the dogleg and BFGS solvers) pass through `forward_closed`:
    # the custom JVP below (implicit function theorem) cannot be transposed; the Delta's fast path can. (The fits'
    # sample-by-sample Jacobian goes through `presolve` and `forward_presolved`, which reverse mode differentiates.)
    transposable: ClassVar[bool] = False
    # whether a fit's program compiles with XLA's own dots rather than YNNPACK's (`jaxcal.fit.core.xla_dots`): they run
    # faster for every closed mechanism measured (8-16 %), but a closure whose Newton solve differentiates in forward
    # mode (this generic one) compiles 0.4-3.4 s longer without YNNPACK; the Delta's fast path, 0.1 s.
    xla_dots: ClassVar[bool] = False
    # whether a fit's Jacobian comes from the tool's parameter twists, `tool_and_twists(robot, a, q, pre, held)` -> (tool,
    # Xi (P, 6)) of one sample (the Delta's); else reverse mode through `forward_presolved`
    twists: ClassVar[bool] = False

    def presolve(self, robot: Robot, a, q):
        """`presolve` (robot: the serving robot, as in a fit's problem)."""
        return presolve(robot, a, q)

    def forward_presolved(self, robot: Robot, a, q, pre) -> Pose:
        """`forward_presolved` (robot: the serving robot, as in a fit's problem)."""
        return forward_presolved(robot, a, q, pre)


class ClosureSolution(NamedTuple):
    """Free joint values, weighted residual norm |v|, the closed flag, solver iterations and the status
    (`jaxcal.closure.track`: CLOSED, UNCLOSED or OTHER_MODE), per sample. ok = (status == CLOSED)."""

    theta_free: jnp.ndarray
    residual_norm: jnp.ndarray
    ok: jnp.ndarray
    steps: jnp.ndarray
    status: jnp.ndarray


jax.export.register_namedtuple_serialization(ClosureSolution, serialized_name="jaxcal.closure.ClosureSolution")


def checked_closure(robot: Robot) -> Closure:
    """The robot's `Closure`, after checking that its pairs and free joints name bodies of the robot."""
    c = robot.closure
    if not isinstance(c, Closure):
        raise ValueError(f"robot {robot.name!r} has no jaxcal.closure.Closure description (closure={c!r})")
    n = len(robot.bodies)
    for p, q, _ in c.pairs:
        if max(p, q) > n:
            raise ValueError(f"robot {robot.name!r}: closure pair ({p}, {q}) names a body beyond {n}")
    for b in c.free:
        if not 1 <= b <= n:
            raise ValueError(f"robot {robot.name!r}: free joint {b} is not a body 1..{n}")
        if robot.bodies[b - 1].inputs:
            raise ValueError(f"robot {robot.name!r}: body {b} is actuated and cannot be a free joint")
    return c


@functools.lru_cache(maxsize=64)  # robots hash by identity: bounded
def open_tree(robot: Robot) -> Robot:
    """The tree with every free joint turned into an input after the actuated ones (closure removed).

    Its joint vector is [joint_variables(q), theta_free]; gains/coupling are applied before. Joints
    that are neither actuated nor free (e.g. one joint of a closure pair) have no input and stay at 0.
    """
    c = checked_closure(robot)
    n_act = robot.n_inputs
    bodies = list(robot.bodies)
    for k, b in enumerate(c.free):
        bodies[b - 1] = dataclasses.replace(bodies[b - 1], inputs=(n_act + k,))
    return robot.replace(bodies=tuple(bodies), closure=None, gains=None, coupling_joint=None, coupling_motor=None,
                         joint_names=robot.joint_names + tuple(f"j{b}" for b in c.free))


def tree_frames(robot: Robot, a, qj, theta_free) -> Pose:
    """All body frames of the open tree for joint variables qj (actuated) and theta_free."""
    return frames_single(open_tree(robot), a, jnp.concatenate([qj, theta_free]))


def euler_parameters(R):
    """Euler parameters (eta0, eta1, eta2, eta3) of a rotation (seed 004 eq A.15-A.18)."""
    return quat_from_matrix(R)


@functools.partial(jax.jit, static_argnums=0)
def closure_residual(robot: Robot, a, qj, theta_free):
    """v of eq 2.67 weighted by Wc^(1/2): stacked g_p - g_q over the closure pairs.

    Compiled (robot static) so that JAX traces it once per argument shapes: a closure solve evaluates it in ~12
    places (corrector, continuation, damped Newton, closure checks, the implicit derivative), and each now
    reuses the cached trace instead of tracing the tree again (Kiwibot, 20 settings: tracing `jc.forward`
    4.5 -> 1.8 s, its jacfwd 8.1 -> 3.1 s; XLA compiles the same program)."""
    c = robot.closure
    f = tree_frames(robot, a, qj, theta_free)
    parts = []
    for p, q, kind in c.pairs:
        parts.append(c.w_position * (f.p[p - 1] - f.p[q - 1]))
        if kind == "full":
            ep, eq = euler_parameters(f.R[p - 1]), euler_parameters(f.R[q - 1])
            sign = jnp.where(jnp.dot(ep, eq) < 0, -1.0, 1.0)  # q and -q are the same rotation
            parts.append(c.w_orientation * (ep - sign * eq))
    return jnp.concatenate(parts)


def _lm():
    return optx.LevenbergMarquardt(rtol=1e-13, atol=1e-14)


def newton_lm(fn, start, max_steps: int, tol: float):
    """Newton/LM hybrid for a closure residual fn(theta) -> v: (theta, steps).

    Each step solves (V^T V + mu I) d = -V^T v with V = dv/dtheta; a step that lowers |v| is kept
    and mu shrinks tenfold (towards plain Gauss-Newton, quadratic near a closed configuration),
    otherwise mu grows tenfold. Stops at |v| <= tol / 100, after max_steps, or when mu exceeds 1e12.
    """
    eye = jnp.eye(start.shape[0], dtype=start.dtype)

    def cond(state):
        _, norm, mu, k = state
        return (norm > 0.01 * tol) & (k < max_steps) & (mu < 1e12)

    def body(state):
        th, norm, mu, k = state
        v, V = value_and_jacfwd(fn, th)
        step = -solve_small(V.T @ V + mu * eye, V.T @ v)
        trial = th + step
        trial_norm = jnp.linalg.norm(fn(trial))
        better = jnp.isfinite(trial_norm) & (trial_norm < norm)
        return (jnp.where(better, trial, th), jnp.where(better, trial_norm, norm),
                jnp.where(better, jnp.maximum(mu * 0.1, 1e-15), mu * 10.0), k + 1)

    init = (start, jnp.linalg.norm(fn(start)), jnp.asarray(1e-6), jnp.asarray(0))
    th, _, _, k = jax.lax.while_loop(cond, body, varying_with(start, init))
    return th, k


def _direct_solve(robot: Robot, a, qj, start):
    """(theta_free, steps): the configured direct solver ("lm" or "newton") from start at (a, qj)."""
    c = robot.closure
    if c.solver == "newton":
        th, k = newton_lm(lambda th: closure_residual(robot, a, qj, th), start, c.max_steps, c.tol)
        return jnp.where(jnp.all(jnp.isfinite(th)), th, start), k
    sol = optx.least_squares(lambda th, args: closure_residual(robot, args[0], args[1], th), _lm(), start,
                             args=(a, qj), max_steps=robot.closure.max_steps, throw=False,
                             adjoint=optx.RecursiveCheckpointAdjoint())
    finite = jnp.all(jnp.isfinite(sol.value))
    return jnp.where(finite, sol.value, start), sol.stats["num_steps"]


def _homotopy(robot: Robot, a, qj, from_home):
    """v(theta, t) along the path from the nominal robot (t = 0) to (a, qj) (t = 1): parameters
    a_ref + t (a - a_ref), and, when the start is the home configuration's (`from_home`, a bool or a traced
    flag), actuated joints qj_home + t (qj - qj_home); a per-sample start (start_fn) is already at qj."""
    a_ref = jnp.asarray(robot.nominal_np)
    qj_ref = jnp.where(from_home, joint_variables(robot, a_ref, jnp.asarray(robot.home_np)), qj)

    def fn(theta, t):
        return closure_residual(robot, a_ref + t * (a - a_ref), qj_ref + t * (qj - qj_ref), theta)

    return fn


def _continuation(robot: Robot, a, qj, start, from_home: bool, active) -> Tracked:
    """`track` from the nominal closed configuration; from the home setting (`from_home`) first and, when the
    start does not close there, again in the parameters only, at this setting. The two attempts are one
    `track` in a loop of two turns (the second inactive unless needed), so XLA compiles the continuation once."""
    tol = robot.closure.tol

    def attempt(i, out):
        again = i == 1
        res = track(_homotopy(robot, a, qj, from_home & ~again), start, 0.01 * tol,
                    active=active & (~again | (from_home & ~out.ref_ok)), loose=tol)
        take = ~again | ~out.ref_ok
        merged = jax.tree_util.tree_map(lambda new, old: jnp.where(take, new, old), res, out)
        return merged._replace(steps=out.steps + res.steps)

    none = Tracked(start, jnp.asarray(False), jnp.asarray(0), jnp.asarray(False))
    return jax.lax.fori_loop(0, 2 if from_home else 1, attempt, varying_with(start, none))


def _is_closed(robot, a, qj, theta):
    norm = jnp.linalg.norm(closure_residual(robot, a, qj, theta))
    return jnp.isfinite(norm) & (norm <= robot.closure.tol)


def _lm_solve(robot: Robot, a, qj, start, mode: str):
    """(theta_free, steps, status) from start (never raises, so a batch survives a bad sample).

    mode "explicit": a caller-given start, solved directly (the caller chose the assembly mode);
    "home" / "start_fn": the closure's own start, solved by the configured solver (see `Closure`)."""
    c = robot.closure
    fn = lambda th: closure_residual(robot, a, qj, th)  # noqa: E731
    if mode == "explicit":
        th, k = _direct_solve(robot, a, qj, start) if c.solver != "track" else damped_newton(fn, start, c.tol, c.max_steps)
        return th, k, jnp.where(_is_closed(robot, a, qj, th), CLOSED, UNCLOSED)
    if c.solver == "track":  # Newton from the start, kept only if it contracts and stays near the start
        th, direct_ok, k = corrector(fn, start, 0.01 * c.tol, loose=c.tol)
    else:
        th, k = _direct_solve(robot, a, qj, start)
        direct_ok = _is_closed(robot, a, qj, th)
    # continuation from the nominal closed configuration (at the home setting when the start is the home one)
    tracked = _continuation(robot, a, qj, start, mode == "home", ~direct_ok)
    th = jnp.where(direct_ok, th, tracked.theta)
    ok = direct_ok | (tracked.reached & _is_closed(robot, a, qj, th))
    # not closed on the branch: does a direct solve from the start close it (another assembly mode)?
    other, k2 = damped_newton(fn, start, c.tol, c.max_steps, active=~ok)
    other_ok = ~ok & _is_closed(robot, a, qj, other)
    status = jnp.where(ok, CLOSED, jnp.where(other_ok, OTHER_MODE, UNCLOSED))
    # an unclosed sample keeps the least-squares point of the direct solve (flagged; finite derivative)
    return jnp.where(ok, th, other), k + tracked.steps + k2, status


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 4))
def _closed_theta(robot: Robot, a, qj, start, mode):
    """theta_free closing the loops; its derivative is the implicit function theorem (eq 2.65-2.69)."""
    return _lm_solve(robot, a, qj, start, mode)


@_closed_theta.defjvp
def _closed_theta_jvp(robot, mode, primals, tangents):
    """d theta = -(V^T V)^-1 V^T (dv/da da + dv/dq dq), V = dv/dtheta at the closed configuration.

    At v = 0 this is the exact implicit derivative of the least-squares solution (the second-order
    term of the Hessian multiplies v); the start has no influence on a converged solution.
    """
    a, qj, start = primals
    da, dqj, _ = tangents
    theta, steps, status = _lm_solve(robot, a, qj, start, mode)
    V = jax.jacfwd(lambda th: closure_residual(robot, a, qj, th))(theta)
    _, dv = jax.jvp(lambda a_, q_: closure_residual(robot, a_, q_, theta), (a, qj), (da, dqj))
    dtheta = -solve_small(V.T @ V, V.T @ dv)
    dtheta = jnp.where(jnp.all(jnp.isfinite(dtheta)), dtheta, 0.0)  # singular V: no closure, flagged anyway
    zero = lambda v: np.zeros(np.shape(v), dtype=jax.dtypes.float0)  # noqa: E731
    return (theta, steps, status), (dtheta, zero(steps), zero(status))


def _solve_single(robot: Robot, a, qj, start, mode: str) -> ClosureSolution:
    c = robot.closure
    if start is None:  # per-sample start from the robot's start_fn
        start = jnp.asarray(jax.lax.stop_gradient(c.start_fn(a, qj)), dtype=jnp.float64)
    theta, steps, status = _closed_theta(robot, a, qj, start, mode)
    norm = jnp.linalg.norm(closure_residual(robot, jax.lax.stop_gradient(a), jax.lax.stop_gradient(qj),
                                            jax.lax.stop_gradient(theta)))
    ok = (status == CLOSED) & jnp.isfinite(norm) & (norm <= c.tol)
    status = jnp.where(ok | (status != CLOSED), status, UNCLOSED)
    return ClosureSolution(theta, jnp.where(jnp.isfinite(norm), norm, jnp.inf), ok, steps, status)


def _start(robot: Robot, start):
    """(start, mode): the explicit start ("explicit"), else None when the closure has a start_fn
    ("start_fn"), else the closure's start at the home setting ("home")."""
    if start is not None:
        return jnp.asarray(start, dtype=jnp.float64), "explicit"
    if robot.closure.start_fn is not None:
        return None, "start_fn"
    return jnp.asarray(robot.closure.start, dtype=jnp.float64), "home"


@exported.jit(static_argnums=(0, 4))
def _solve_batched(robot: Robot, a, q, start, mode) -> ClosureSolution:
    def one(qi):
        return _solve_single(robot, a, joint_variables(robot, a, qi), start, mode)

    return map_leading_axes(one, q)


def solve(robot: Robot, a, q, start=None) -> ClosureSolution:
    """Close the loops for actuator settings q (..., n_inputs): free joints, |v|, ok flag per sample.

    start: theta_free start (default `robot.closure.start_fn(a, qj)` per sample when set, else
    `robot.closure.start`, the robot's assembly mode).
    """
    checked_closure(robot)
    a = jnp.asarray(a, dtype=jnp.float64)
    q = jnp.asarray(q, dtype=jnp.float64)
    return _solve_batched(robot, a, q, *_start(robot, start))


def failed_pose(pose: Pose, ok) -> Pose:
    """The tool pose where ok, else a penalty pose: FAIL_OFFSET metres added to each coordinate and the
    frame turned by FAIL_ROTATION, both without derivative. Finite, far from any reading of every
    device kind (position, pose, orientation-only, angles, ranges), so a fit step that makes a sample
    unclosable raises the cost and is rejected, as the thesis' Inf (§3.3)."""
    sg = jax.lax.stop_gradient
    p = jnp.where(ok, pose.p, sg(pose.p) + FAIL_OFFSET)
    R = jnp.where(ok, pose.R, sg(pose.R) @ jnp.asarray(FAIL_ROTATION))
    return Pose(R, p)


def _forward_single(robot: Robot, a, qi, start, mode) -> Pose:
    qj = joint_variables(robot, a, qi)
    sol = _solve_single(robot, a, qj, start, mode)
    f = tree_frames(robot, a, qj, sol.theta_free)
    return failed_pose(Pose(f.R[robot.tip], f.p[robot.tip]), sol.ok)


@functools.partial(jax.jit, static_argnums=(0, 4))
def _forward_batched(robot: Robot, a, q, start, mode) -> Pose:
    return map_leading_axes(lambda qi: _forward_single(robot, a, qi, start, mode), q)


def forward_closed(robot: Robot, a, q, start=None) -> Pose:
    """Tool frame of a closed mechanism (closure solved inside) for q (..., n_inputs).

    A sample whose loops do not close on the nominal branch gets the penalty pose of `failed_pose`;
    check `solve(...).ok` / `.status` or `closed(...)` for the flags.
    """
    checked_closure(robot)
    a = jnp.asarray(a, dtype=jnp.float64)
    q = jnp.asarray(q, dtype=jnp.float64)
    return _forward_batched(robot, a, q, *_start(robot, start))


def presolve(robot: Robot, a, q):
    """The closure of each sample of q (..., n_inputs) without derivative: (theta_free, ok) of `solve` at a, for
    `forward_presolved`."""
    sol = solve(robot, jax.lax.stop_gradient(a), jax.lax.stop_gradient(q))
    return sol.theta_free, sol.ok


def _implicit_step(robot: Robot, a, qj, theta):
    """theta with the implicit derivative of eq 2.65-2.69 and no change of value: theta + d - stop_gradient(d), with
    d = -(V^T V)^-1 V^T v(a, qj, theta) and V = dv/dtheta held fixed (`_closed_theta_jvp`'s derivative, written so
    that reverse mode passes through it)."""
    sg = jax.lax.stop_gradient
    V = jax.jacfwd(lambda th: closure_residual(robot, sg(a), sg(qj), th))(theta)
    v = closure_residual(robot, a, qj, theta)
    d = -solve_small(V.T @ V, V.T @ v)
    d = jnp.where(jnp.all(jnp.isfinite(sg(d))), d, 0.0)  # singular V: no closure, flagged anyway
    return theta + d - sg(d)


def forward_presolved(robot: Robot, a, q, pre) -> Pose:
    """`forward_closed` from the closure solved beforehand (`presolve` at the same a and q): the same tool poses and
    derivatives, by plain autodiff through `_implicit_step` (forward or reverse mode).

    A fit differentiates it in reverse mode sample by sample (`jaxcal.fit.core.data_residual_and_jacobian`): the
    closure is solved once for the batch, and each sample's readings take as many reverse passes as they have
    components instead of one tangent per parameter through the custom JVP."""
    a = jnp.asarray(a, dtype=jnp.float64)
    theta, ok = pre
    lead = q.shape[:-1]

    def one(qi, th, k):
        qj = joint_variables(robot, a, qi)
        f = tree_frames(robot, a, qj, _implicit_step(robot, a, qj, jax.lax.stop_gradient(th)))
        return failed_pose(Pose(f.R[robot.tip], f.p[robot.tip]), k)

    out = jax.vmap(one)(q.reshape(-1, q.shape[-1]), theta.reshape(-1, theta.shape[-1]), ok.reshape(-1))
    return jax.tree_util.tree_map(lambda v: v.reshape(lead + v.shape[1:]), out)


@exported.jit(static_argnums=(0,))
def _tool_of_solution(robot: Robot, a, q, theta_free, ok) -> Pose:
    def one(qi, th, k):
        f = tree_frames(robot, a, joint_variables(robot, a, qi), th)
        return failed_pose(Pose(f.R[robot.tip], f.p[robot.tip]), k)

    lead = q.shape[:-1]
    out = jax.vmap(one)(q.reshape(-1, q.shape[-1]), theta_free.reshape(-1, theta_free.shape[-1]), ok.reshape(-1))
    return jax.tree_util.tree_map(lambda v: v.reshape(lead + v.shape[1:]), out)


def forward_with_status(robot: Robot, a, q) -> tuple[Pose, jax.Array]:
    """(tool pose, closure status) per sample from one closure solve: the solve of `closure_status`
    (compiled once and shared with the fits' unclosed-sample checks), then the open tree at the
    closed free joints, which compiles in a fraction of a differentiable `forward_closed`. Unclosed
    samples get the penalty pose of `failed_pose`, as in `forward_closed`."""
    checked_closure(robot)
    a = jnp.asarray(a, dtype=jnp.float64)
    q = jnp.asarray(q, dtype=jnp.float64)
    own = getattr(robot.closure, "solve", None)
    sol = own(robot, a, q) if own is not None else solve(robot, a, q)
    return _tool_of_solution(robot, a, q, sol.theta_free, sol.ok), sol.status


def closed(robot: Robot, a, q, start=None):
    """Per-sample boolean flags: True where the loops close to |v| <= tol. A mechanism-specific
    closure (one with its own `solve`, e.g. the Delta's) answers for itself unless a start is given."""
    own = getattr(robot.closure, "solve", None)
    if own is not None and start is None:
        return own(robot, a, q).ok
    return solve(robot, a, q, start).ok


def closure_status(robot: Robot, a, q, start=None):
    """Per-sample status (`jaxcal.closure.track`: 0 CLOSED, 1 UNCLOSED, 2 OTHER_MODE), answered by a
    mechanism-specific closure for itself as in `closed`."""
    own = getattr(robot.closure, "solve", None)
    if own is not None and start is None:
        return own(robot, a, q).status
    return solve(robot, a, q, start).status


def all_frames(robot: Robot, a, q, start=None) -> Pose:
    """Every body frame of the closed mechanism for one actuator setting q (n_inputs,)."""
    a = jnp.asarray(a, dtype=jnp.float64)
    q = jnp.asarray(q, dtype=jnp.float64)
    qj = joint_variables(robot, a, q)
    sol = solve(robot, a, q, start)
    return tree_frames(robot, a, qj, sol.theta_free)
