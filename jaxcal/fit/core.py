"""The calibration core: one problem, one start, one solve path, one typed result.

Every client (identify, Monte Carlo, fleet, cross-validation, the gap baseline, the CLI) builds a
`Problem` and calls `calibrate` (or, for a batch of problems that differ only in their data,
`solve_batch`). Nothing else in jaxcal runs its own copy of the solve path.

The unknowns x are the full parameter vector (robot parameters, then device parameters). The
solver minimises the stacked residual (seed 004 eq 3.12 with bounds as a penalty, §3.3)

    r(x) = [ w * (y - read(forward(a, q), d))               data rows, one per reading component
             sqrt(mu) m * (x - x_ref) / s                   bias toward the prior on estimated entries
             (1 - m) * (x - x_ref) / s                      pin: entries not estimated stay at x_ref
             1e6 m * max(x - ub, lb - x, 0) / s ]           bound penalty

with m the 0/1 mask of estimated entries and s their typical size (`x_scale`). Pinning instead
of slicing keeps one shape for every stage (frames-only fit, base-set fit, bias stages, folds),
so one compiled solver serves them all; a sample weight of 0 removes a sample exactly, so a
fold is a weight mask and gives the same optimum as the subset.

The data rows come from a residual model (`Problem.model`): the robot measured by the device
(`RobotDevice`, every client but one), or any object with the same interface (names, units, priority,
x_scale(), residuals(x, q, y, cov, w) with per-sample covariates cov): the gap diagnosis' refits pass
its `GapModel` (geometry, device and effect parameters), so they run on this solve path too.

The start is the same for every robot and device (`start`): the device frame by closed-form
rigid registration of the readings onto the nominal model's points (any rotation, any distance),
kept only where it lowers the cost, then the frames-only fit of every free device parameter.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import hashlib
import threading
import time
import warnings

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from jaxcal import compiled, exported
from jaxcal.closure.core import forward_with_status
from jaxcal.fit import buckets
from jaxcal.fit.base import base_set, small_lstsq, upper_factor
from jaxcal.fit.csvfile import DataError
from jaxcal.fit.lm import LevenbergMarquardt, residual_and_jacobian
from jaxcal.forward import forward
from jaxcal.kin import twists
from jaxcal.kin.model import Robot
from jaxcal.kin.pose import Pose
from jaxcal.measure.devices import Device
from jaxcal.names import check_names

# The one name -> solver map (CLI, job files, `identify(solver=...)`); an optimistix solver object works too.
SOLVERS = {
    "lm": LevenbergMarquardt,  # jaxcal.fit.lm: compiles ~1.6x faster than optimistix's (its docstring)
    "lm_optimistix": lambda rtol, atol: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
    # normal equations by Cholesky: ~1.7x faster than QR for tall Jacobians, less robust with noise (docs/identification.md)
    "lm_normal": lambda rtol, atol: optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky())),
    "gn": lambda rtol, atol: optx.GaussNewton(rtol=rtol, atol=atol),
    "gn_normal": lambda rtol, atol: optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky())),
    "dogleg": lambda rtol, atol: optx.Dogleg(rtol=rtol, atol=atol),
    "bfgs": lambda rtol, atol: optx.BFGS(rtol=rtol, atol=atol),
}
# Base set: QR pivots below this share of the largest are dependent. Seed 001's eq 34 (n eps) keeps columns
# whose dependency is exact only up to round-off: the Delta's Table 4.6 (values rounded to 4 digits) leaves
# ~1e-13, and MRR-1's six-parameter modules left pivots of 1e-14 that made the estimate's condition number
# 1e14-1e15 (parameters whose values are arbitrary). One rule for every robot.
BASE_TOL = 1e-10
# Frames-only fit: device parameters whose QR pivot (typical-size units) is below this share of the largest
# are left at their prior until the full fit (`frames_estimated`). The Delta's tool offset sits at 1e-6 (must be
# held); a pose probe turning by 0.05 degrees puts it at ~1e-3, where the frames-only fit still finds it to 2 cm
# and holding it (tolerance 1e-2) made the full fit move two base lengths by 1.2 m to absorb it.
START_TOL = 1e-4
# Frames-only fit: it stops, converged, at a step predicted to lower its cost by at most this share of it (`lm.advance`'s
# stop), that step not evaluated. It is the start of the full fit, which refits every device parameter, so its cost
# need not be nearer its optimum than that (Stanford arm, 200 readings: its second step lowered the cost by 8e-9 of it
# for poses, 3e-7 for positions, and cost a residual-and-Jacobian evaluation of the 2 the start made).
START_STOP = 1e-6
# The fits' stop by Bates and Watts' relative offset ("A relative offset orthogonality convergence criterion for
# nonlinear least squares", Technometrics 23, 1981): a step whose predicted decrease |r|^2 - |r + J v|^2 is at most
# OFFSET_TOL^2 p s^2 (p unknowns, s^2 = |r|^2 / (readings - p)) would move the estimate by at most OFFSET_TOL of the
# radius of its confidence region; the fit ends there, converged, that step not evaluated (`offset_stop`). 1e-3 is
# Bates and Watts' value. A fit of noisy readings ends one evaluation earlier than at the round-off stop alone (Stanford
# arm, 200 poses, 1e-5 noise: the main fit's third step, predicted to lower the cost by 3e-10 of it, was evaluated for
# nothing); a noise-free fit (s^2 at round-off) goes on as before.
OFFSET_TOL = 1e-3
# Final stage (`polish`): every free parameter, biased toward the base-set estimate with this mu, kept only when
# it lowers the cost by more than fitting noise would (F ratio above POLISH_F). The base set is chosen at the
# start; in the nonlinear model the parameters it holds are not exactly redundant at the solution (a UR10 URDF
# chain, 1 mm / 1 mrad errors, 40 positions, 0.02 mm noise: 0.18 mm true error left, cost 2090 for 120 readings;
# polished 0.014 mm, cost 83). mu 1e-2 and 1e-4 gave the same error with moves of 0.2 mm; 1e-6 and below let the
# undetermined directions wander by 0.2-1.2 m/rad without converging.
POLISH_BIAS = 1e-2
POLISH_F = 4.0
NO_EFFECT_AT_SOLUTION = 1e-10  # a held column below this share of the largest (typical-size units) has no effect at x
# Samples per vmapped chunk of the reverse-mode data Jacobian (`data_residual_and_jacobian`).
JACOBIAN_CHUNK = 2048
STEP_WIDTH_ROUND = 8  # `Problem.step_width` is a multiple of this: problems that free a few entries more or less share a program
# Readings whose best similarity registration onto the model needs one of these scales are in another unit.
UNIT_SCALES = {"mm": 1e-3, "cm": 1e-2, "inch": 0.0254}


def make_solver(solver, rtol: float, atol: float):
    """The solver of a name of `SOLVERS` (jaxcal's LM or an optimistix solver), or the given object unchanged."""
    if not isinstance(solver, str):
        return solver
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {tuple(SOLVERS)} or an optimistix solver")
    return SOLVERS[solver](rtol, atol)


def x_scale(units) -> np.ndarray:
    """Typical size of a parameter change: 0.01 (m or rad) for geometry, 1 for gains and scales."""
    return np.array([1.0 if u in ("gain", "scale") else 0.01 for u in units])


@functools.partial(jax.jit, static_argnums=(0, 1))
def readings(robot: Robot, device: Device, a_full, q):
    """Readings (N, ...) the model expects at joint values q (N, n) for the full vector a_full = [robot, device].
    Compiled (robot and device static): called eagerly, the kinematics would run op by op."""
    device.check_robot(robot)  # at trace time
    nr = robot.n_params
    return jax.vmap(device.read, (0, None))(forward(robot, a_full[:nr], q), a_full[nr:])


@functools.partial(jax.jit, static_argnums=(0,))
def read_poses(device: Device, tool: Pose, d):
    """The device's readings (N, ...) of the tool poses (N, ...) with device parameters d, compiled (device static)."""
    return jax.vmap(device.read, (0, None))(tool, d)


_PREDICTED: collections.OrderedDict = collections.OrderedDict()
_PREDICTED_MAX = 8  # the last readings evaluated, by robot, device and content of a_full and q
compiled.register(_PREDICTED.clear)
# Guards _PREDICTED and _COMPILED: solves run from several threads at once (`fit.bias.heldout_scores`' folds), and a
# look-up followed by move_to_end must not meet another thread's eviction of the same key.
_CACHE_LOCK = threading.Lock()


def predicted(robot: Robot, device: Device, a_full, q) -> np.ndarray:
    """`readings` evaluated from Python, without derivative (a read-only array). A closed mechanism's tool comes from
    one closure solve (`jaxcal.closure.forward_with_status`: the solve that the fits' unclosed-sample check compiles
    anyway, then the open tree at the closed joints), not from the differentiable closed forward, whose compile took
    ~4 s on the Delta for every sample count; an open chain runs `readings` itself.

    The last _PREDICTED_MAX results are kept by content (a digest of a_full and q): one `identify` reads the same
    point up to five times (the costs of the start, the solver's scaling, the polish, the health checks, the RMS
    errors and the covariance), 13 evaluations of ~0.45 ms each on the Stanford arm at 200 positions."""
    a_full, q = np.asarray(a_full, float), np.asarray(q, float)
    key = (robot, device, q.shape, hashlib.blake2b(a_full.tobytes() + q.tobytes(), digest_size=20).digest())
    with _CACHE_LOCK:
        if key in _PREDICTED:
            _PREDICTED.move_to_end(key)
            return _PREDICTED[key]
    q_bucket = buckets.repeat_row(q, buckets.sample_bucket(len(q)), 0)  # one program per bucket of sample counts
    if robot.closure is None:
        out = np.asarray(readings(robot, device, a_full, q_bucket))[:len(q)]
    else:
        device.check_robot(robot)
        tool, _ = forward_with_status(robot, a_full[:robot.n_params], q_bucket)
        out = np.asarray(read_poses(device, tool, a_full[robot.n_params:]))[:len(q)]
    out.flags.writeable = False
    with _CACHE_LOCK:
        _PREDICTED[key] = out
        if len(_PREDICTED) > _PREDICTED_MAX:
            _PREDICTED.popitem(last=False)
    return out


@functools.partial(jax.jit, static_argnums=(0,))
def misfit(device: Device, read, y, w):
    """w * (measured - predicted) (N, m) from the predicted readings."""
    return jax.vmap(device.residual)(read, y) * w


def residuals(robot: Robot, device: Device, a_full, q, y, w):
    """Weighted residuals (N, m) of all samples: w * (measured - predicted), differentiable (the solver traces it:
    `readings`, then `misfit`). From Python, `weighted_residuals` evaluates it through `predicted`."""
    return misfit(device, readings(robot, device, a_full, q), y, w)


def open_residual_and_jacobian(robot: Robot, device: Device, x, q, y, w, robot_held=False, pre=None):
    """(r, J) of the data rows (`RobotDevice.residual_and_jacobian`) from the parameters' twists, sample by sample: the
    tool frames and the world twist Xi of every robot parameter come from one forward pass (an open chain:
    `jaxcal.kin.twists.tools_and_twists`; a closure with `Closure.twists`, from its closure presolved for the batch,
    pre: `Closure.tool_and_twists`); the reading's m vector-Jacobian products give dr/dd and dr/dT, which
    `twists.wrench` turns into the derivative along each unit twist of the tool (m, 6), and dr/da = that times Xi.
    No reverse pass runs through the chain. Against m reverse passes (Stanford arm, 200 readings, this 2-core CPU):
    the first identify 3.2 -> 2.3 s (positions) and 4.0 -> 3.0 s (poses), mostly the solver's XLA compile; a pose
    residual and Jacobian 1.6-1.8 -> 1.1 ms of kernels (docs/benchmarks.md, 2026-11-29, eleventh session).
    robot_held (traced): the robot's columns are 0 and Xi is not computed."""
    nr = robot.n_params
    a, d = x[:nr], x[nr:]

    def one(sample):
        qi, yi, wi, pi = sample
        if pre is None:
            tools, Xi = twists.tools_and_twists(robot, a, qi, robot_held)
        else:
            tools, Xi = robot.closure.tool_and_twists(robot, a, qi, pi, robot_held)

        def reading(T, dd):
            T1 = jax.tree_util.tree_map(lambda v: v[None], T)
            return misfit(device, jax.vmap(device.read, (0, None))(T1, dd), yi[None], wi[None]).reshape(-1)

        r, pullback = jax.vjp(reading, tools, d)
        tool_bar, J_d = jax.vmap(pullback)(jnp.eye(r.shape[0], dtype=r.dtype))
        along = twists.wrench(jax.tree_util.tree_map(lambda v: v[None], tools), tool_bar)  # (m, [tips,] 6)
        # a dot, so that `along` is computed once: as a product summed, XLA fused it into the loop that writes J and
        # recomputed the reading's pullback (a pose's rotation log, sines and cosines) for each of the robot's columns
        J_a = jnp.einsum("mtk,tpk->mp", along.reshape(r.shape[0], -1, 6), Xi.reshape(-1, nr, 6))
        return r, jnp.concatenate([J_a, J_d], axis=1)

    r, J = jax.lax.map(one, (q, y, w, pre), batch_size=JACOBIAN_CHUNK)
    return r.reshape(-1), J.reshape(-1, x.shape[0])


@dataclasses.dataclass(frozen=True)
class RobotDevice:
    """The residual model of a robot measured by a device: x = [robot parameters, device parameters], no
    covariates. Hashes by its robot and device (a static jit argument: one compiled solver per pair)."""

    robot: Robot
    device: Device

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.robot.names) + tuple(self.device.names)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(self.robot.units) + tuple(self.device.units)

    @property
    def priority(self) -> np.ndarray:
        return np.concatenate([self.robot.priority, self.device.priority])

    def x_scale(self) -> np.ndarray:
        return x_scale(self.units)

    @property
    def jacobian_mode(self) -> str:
        """Sample by sample (`residual_and_jacobian`: an open chain from its parameters' twists, a closed mechanism
        in reverse mode after its closure is solved for the batch, `presolve`)."""
        return "reverse"

    def presolve(self, x, q):
        """The closure of each sample at x, without derivative (`Closure.presolve`), for `residuals`' pre; None
        for an open chain."""
        if self.robot.closure is None:
            return None
        return self.robot.closure.presolve(self.robot, x[: self.robot.n_params], q)

    def residual_and_jacobian(self, x, q, y, w, robot_held=False):
        """(r, J): the data rows (N*m,) at x and their Jacobian (N*m, P), sample by sample in chunks of
        JACOBIAN_CHUNK. robot_held (traced): the robot's columns are 0, what a fit of device parameters alone needs
        (the start's frames-only fit). An open chain: `open_residual_and_jacobian`. A closed mechanism: its closure
        solved for the batch first (`presolve`), then, where the closure gives the tool's parameter twists
        (`Closure.twists`: the Delta), `open_residual_and_jacobian` from those; else reverse mode, the reading's m
        vector-Jacobian products giving dr/dd and the cotangents of T, which the kinematics' pullback takes to dr/da
        (not run when robot_held: Stanford arm, 200 positions, one evaluation ~3x cheaper)."""
        if self.robot.closure is None:
            return open_residual_and_jacobian(self.robot, self.device, x, q, y, w, robot_held)
        pre = self.presolve(x, q)
        closure = self.robot.closure
        if closure.twists:
            return open_residual_and_jacobian(self.robot, self.device, x, q, y, w, robot_held, pre)
        nr = self.robot.n_params
        a, d = x[:nr], x[nr:]

        def one(sample):
            qi, yi, wi, pi = sample
            tool, kinematics_pullback = jax.vjp(
                lambda a_r: closure.forward_presolved(self.robot, a_r, qi[None], jax.tree_util.tree_map(lambda v: v[None], pi)), a)
            r, reading_pullback = jax.vjp(
                lambda T, dd: misfit(self.device, jax.vmap(self.device.read, (0, None))(T, dd), yi[None], wi[None]).reshape(-1),
                tool, d)
            tool_bar, J_d = jax.vmap(reading_pullback)(jnp.eye(r.shape[0], dtype=r.dtype))
            J_a = jax.lax.cond(robot_held, lambda: jnp.zeros((r.shape[0], nr), r.dtype),
                               lambda: jax.vmap(kinematics_pullback)(tool_bar)[0])
            return r, jnp.concatenate([J_a, J_d], axis=1)

        r, J = jax.lax.map(one, (q, y, w, pre), batch_size=JACOBIAN_CHUNK)
        return r.reshape(-1), J.reshape(-1, x.shape[0])

    def residuals(self, x, q, y, cov, w, pre=None):
        """w * (y - read(forward(a, q), d)) (N, m); cov is ignored. With pre (`presolve` at the same x and q) a
        closed mechanism's tool comes from `Closure.forward_presolved`, which reverse mode differentiates."""
        if pre is None:
            return residuals(self.robot, self.device, x, q, y, w)
        nr = self.robot.n_params
        self.device.check_robot(self.robot)
        tool = self.robot.closure.forward_presolved(self.robot, x[:nr], q, pre)
        return misfit(self.device, jax.vmap(self.device.read, (0, None))(tool, x[nr:]), y, w)


def prior_rows(x, args):
    """The rows after the data rows at the full vector x: sqrt(mu) m (x - x_ref) / s + (1 - m) (x - x_ref) / s
    (bias and pin), then the bound penalty 1e6 m max(x - ub, lb - x, 0) / s (module docstring)."""
    m = args["mask"]
    scaled = (x - args["a_ref"]) / args["x_scale"]
    over = jnp.maximum(x - args["ub"], 0.0) + jnp.maximum(args["lb"] - x, 0.0)
    return jnp.concatenate([jnp.sqrt(args["mu"]) * m * scaled + (1.0 - m) * scaled, 1e6 * m * over / args["x_scale"]])


def data_rows(model, a_full, args):
    """The data rows (N*m,) of the stacked residual at a_full."""
    return model.residuals(a_full, args["q"], args["y"], args["cov"], args["w"]).reshape(-1)


def model_stacked(model, x, args):
    """The stacked residual r(x) of the module docstring for a residual model; `args` holds the arrays of a
    `Problem` (mu: a number, or one per entry of x)."""
    return jnp.concatenate([data_rows(model, jnp.where(args["mask"] > 0, x, args["a_ref"]), args), prior_rows(x, args)])


def stacked(robot: Robot, device: Device, x, args):
    """The stacked residual r(x) of the module docstring; `args` holds the arrays of a `Problem`."""
    return model_stacked(RobotDevice(robot, device), x, args)


def stacked_scaled(model, z, args):
    """`model_stacked` in the scaled unknowns z = (x - a_ref) / x_scale, the variables the solver works in.

    Levenberg-Marquardt damps every unknown alike (optimistix adds lambda I), so in raw units a metre,
    a radian and a gain of 1 would be one step size; in z one unit is a typical change of each entry
    (MINPACK's diagonal scaling with fixed scales). On the Delta (seed 004 Table 4.6: lengths of 0.1-0.4 m,
    angles, 9 tracker-frame entries) raw units took > 200 steps where z takes tens."""
    return model_stacked(model, args["a_ref"] + args["x_scale"] * z, args)


def jacobian_mode(model) -> str:
    """"reverse" when the residual model's samples may be differentiated one by one in reverse mode (its
    `jacobian_mode`), else "forward" (a model without `presolve` whose closure's implicit derivative is a custom_jvp:
    the gap models of closed mechanisms)."""
    return getattr(model, "jacobian_mode", "forward")


def data_residual_and_jacobian(model, a_full, q, y, cov, w):
    """(r, J): the weighted data residuals (N*m,) at a_full and their Jacobian dr/da_full (N*m, P).

    Each sample's m residual components depend on a_full and on that sample's own q, y, cov, w only. In reverse
    mode J is built a sample at a time from m vector-Jacobian products (one primal pass each sample), vmapped over
    the samples: m reverse passes instead of P forward tangents through the kinematics (Stanford arm, 200
    positions, P = 52: 0.74 ms instead of 4.5 ms on this 2-core CPU), in chunks of JACOBIAN_CHUNK samples (a loop
    over chunks, each vmapped) so that the reverse passes' intermediates stay bounded (100,000 positions: peak
    RSS of `identify` 2.0 GB in one batch). A model with a `presolve(a_full, q)` (a closed mechanism) solves what has
    no derivative (the closure) once for the batch, and each sample's pass starts from its part (`pre`): solved
    inside the vmapped passes, a loop that runs until its slowest lane ends would run for every sample. Forward
    mode: the pushforwards of the unit vectors through all rows, vmapped, sharing one primal pass
    (`lm.residual_and_jacobian`: one closure solve, not two)."""
    if jacobian_mode(model) != "reverse":  # the pushforwards of the unit vectors share one primal pass (one closure solve)
        return residual_and_jacobian(lambda a, _: model.residuals(a, q, y, cov, w).reshape(-1), a_full, None)

    presolve = getattr(model, "presolve", None)
    pre = None if presolve is None else presolve(a_full, q)
    given = (lambda p: {}) if pre is None else (lambda p: {"pre": jax.tree_util.tree_map(lambda v: v[None], p)})

    def one(sample):
        qi, yi, ci, wi, pi = sample
        r, pullback = jax.vjp(lambda a: model.residuals(a, qi[None], yi[None], ci[None], wi[None], **given(pi)).reshape(-1),
                              a_full)
        return r, jax.vmap(pullback)(jnp.eye(r.shape[0], dtype=r.dtype))[0]

    r, J = jax.lax.map(one, (q, y, cov, w, pre), batch_size=JACOBIAN_CHUNK)
    return r.reshape(-1), J.reshape(-1, a_full.shape[0])


@functools.partial(jax.jit, static_argnums=0)
def scaled_residual_and_jacobian(model, z, args):
    """(r, J) of `stacked_scaled` at z, J with every column: the data rows by `data_residual_and_jacobian` (chain
    rule through x = a_ref + x_scale z; the entries not estimated are held at a_ref, and their columns are the data
    rows' derivative there, which the solver leaves out of its steps and returns: `lm.least_squares`'s free), the
    prior rows by forward mode (elementwise). Compiled (model static): `lm.least_squares` traces it for the shapes
    of its state and again in its loop, and the second trace reuses the first (3-D four-bar, 60 positions: tracing
    the solver 1.88 -> 1.61 s)."""
    m, a_ref, s = args["mask"], args["a_ref"], args["x_scale"]
    x = jnp.where(m > 0, a_ref + s * z, a_ref)
    if isinstance(model, RobotDevice) and jacobian_mode(model) == "reverse":  # no robot entry estimated: none differentiated
        held = jnp.all(m[:model.robot.n_params] == 0) & (args["full"] <= 0)  # unless every column is asked for
        r_d, J_a = model.residual_and_jacobian(x, args["q"], args["y"], args["w"], held)
    else:
        r_d, J_a = data_residual_and_jacobian(model, x, args["q"], args["y"], args["cov"], args["w"])
    r_p, J_p = scaled_prior_rows_and_jacobian(z, args)
    return jnp.concatenate([r_d, r_p]), jnp.concatenate([J_a * s, J_p])


def scaled_prior_rows_and_jacobian(z, args):
    """(r, J) of `stacked_scaled`'s rows after the data rows (`prior_rows`) at z. Row k of each of its two blocks
    depends on z_k alone, so J is two diagonal blocks [diag(d1); diag(d2)], whose diagonals are one forward-mode
    derivative along z's unit vectors summed (tangent 1), instead of P pushforwards of the unit vectors on dense
    (2P, P) arrays in every evaluation (Delta, P = 166: the solver's first 8 steps 31.9-36.4 -> 30.3-30.6 ms)."""
    r, d = jax.jvp(lambda u: prior_rows(args["a_ref"] + args["x_scale"] * u, args), (z,), (jnp.ones_like(z),))
    P = z.shape[0]
    return r, jnp.concatenate([jnp.diag(d[:P]), jnp.diag(d[P:])])


def given_start(z0, args):
    """(r, J, given) of `stacked_scaled` at z0 from the data rows' residual and Jacobian in args["start"] (r (N*m,), J
    (N*m, P) in x, the solver's weights, at x = a_ref + x_scale z0), the prior rows evaluated here: `lm.starting_with`'s
    start. given: args["start"]["given"] > 0 (else the arrays are placeholders and the solver evaluates z0 itself)."""
    start = args["start"]
    r_p, J_p = scaled_prior_rows_and_jacobian(z0, args)
    return (jnp.concatenate([start["r"], r_p]), jnp.concatenate([start["J"] * args["x_scale"], J_p]), start["given"] > 0)


@dataclasses.dataclass(frozen=True)
class Settings:
    """Static solver settings (hashable: they select the compiled solver).

    rtol, atol: the solvers stop after an accepted step that changes every scaled unknown z by less than
    atol + rtol |z| and every residual r_i by less than atol + rtol |r_i|. In z one unit is a typical change
    (1 cm, 0.01 rad, a gain of 1), so the defaults stop at ~1e-8 m; the stricter 1e-8 / 1e-10 gave the same
    estimate and RMS (6 digits, Stanford arm, 200 poses) after 24 steps instead of 6: past the optimum every
    proposed step is rejected until the trust region has shrunk to round-off. The core's LM also stops after an
    accepted step whose predicted cost decrease is at round-off (`lm.ROUND_OFF`), and the fits of `calibrate` at
    their relative offset (`OFFSET_TOL`; 0 there runs them to these tolerances alone)."""

    solver: object = "lm"
    max_steps: int = 200
    rtol: float = 1e-6
    atol: float = 1e-8


def stacked_basis(model, z, args):
    """The stacked residual in the unknowns z (K,) of a basis S (P, K) with orthogonal columns: x = a_ref + S (m z).

    For clients that estimate a few of many parameters (the gap refits: geometry and the selected effects of
    a model with every effect's parameters): each column of S picks one entry at its typical size, so the
    Jacobian has K columns, not P; m (K,) is 0 on unused (padding) columns, which the rows (1 - m) z pin at 0.
    Rows: the data rows at x, sqrt(mu) m z (mu a number or (K,)), (1 - m) z, and the bound penalty
    1e6 max(x - ub, lb - x, 0) / x_scale on the entries S moves."""
    x = basis_point(z, args)
    return jnp.concatenate([data_rows(model, x, args), basis_prior_rows(z, args)])


def basis_point(z, args):
    """The full vector x = a_ref + S (m z) of the basis unknowns z."""
    return args["a_ref"] + args["S"] @ (args["mask"] * z)


def basis_prior_rows(z, args):
    """The rows of `stacked_basis` after the data rows."""
    m, x = args["mask"], basis_point(z, args)
    moved = jnp.any(args["S"] != 0, axis=1)
    over = jnp.maximum(x - args["ub"], 0.0) + jnp.maximum(args["lb"] - x, 0.0)
    return jnp.concatenate([jnp.sqrt(args["mu"]) * m * z + (1.0 - m) * z, 1e6 * moved * over / args["x_scale"]])


def basis_residual_and_jacobian(model, z, args):
    """(r, J) of `stacked_basis` at z: the data rows by `data_residual_and_jacobian` times dx/dz = S diag(m), the
    prior rows by forward mode."""
    r_d, J_a = data_residual_and_jacobian(model, basis_point(z, args), args["q"], args["y"], args["cov"], args["w"])
    r_p, J_p = residual_and_jacobian(basis_prior_rows, z, args)
    return jnp.concatenate([r_d, r_p]), jnp.concatenate([J_a @ (args["S"] * args["mask"]), J_p])


def basis_coordinates(S, dx):
    """z with S z = dx for the part of dx in the span of S's orthogonal columns: z_k = s_k . dx / |s_k|^2."""
    return (S.T @ dx) / jnp.maximum(jnp.sum(S**2, axis=0), 1e-300)


def solver_settings(solver="lm", max_steps: int | None = None, rtol: float | None = None, atol: float | None = None) -> Settings:
    """`Settings` with the given fields, the defaults of `Settings` for those left None (CLI and API callers)."""
    given = dict(solver=solver, max_steps=max_steps, rtol=rtol, atol=atol)
    return dataclasses.replace(Settings(), **{k: v for k, v in given.items() if v is not None})


def _solve_one(x0, args, limit, model, settings: Settings, width: int | None = None):
    """One LM run from x0, at most min(settings.max_steps, limit) iterations: in z = (x - a_ref) / x_scale
    (`stacked_scaled`), or in the basis args["S"] when args has one (`stacked_basis`). Returns (x, converged,
    steps, final cost, cost history, r, J): the history is `lm.LMResult.history` for the core's LM, empty (shape
    (0,)) for the optimistix solvers; r and J are the stacked residual and its Jacobian in z at x (the core's LM;
    empty for the others; out of a basis, every column, the entries not estimated too), which `Problem.jacobian`
    reads with limit 0 and `solve` after a fit. width: the core LM's step width (`Problem.step_width`). args["start"]
    (`Problem.solver_arrays`), when given, holds the data rows' r and J at x0, which the core's LM then does not
    evaluate again (`given_start`; not in a basis)."""
    slv = make_solver(settings.solver, settings.rtol, settings.atol)
    reverse = jacobian_mode(model) == "reverse"
    if "S" in args:
        fn = functools.partial(stacked_basis, model)
        jac = functools.partial(basis_residual_and_jacobian, model) if reverse else None
        z0 = basis_coordinates(args["S"], x0 - args["a_ref"])
        to_x = lambda z: basis_point(z, args)  # noqa: E731
    else:
        fn = functools.partial(stacked_scaled, model)
        jac = functools.partial(scaled_residual_and_jacobian, model)
        z0 = (x0 - args["a_ref"]) / args["x_scale"]
        to_x = lambda z: args["a_ref"] + args["x_scale"] * z  # noqa: E731
    if isinstance(slv, LevenbergMarquardt):
        start = given_start(z0, args) if "start" in args and "S" not in args else None
        data_rows = None if "S" in args else args["w"].size  # then the prior rows (2P) have one entry each
        res = slv(fn, z0, args, settings.max_steps, jac, limit, None if "S" in args else args["mask"], width, start, data_rows,
                  args.get("stop", 0.0))
        return to_x(res.z), res.converged, res.steps, res.cost, res.history, res.r, res.J
    sol = optx.least_squares(fn, slv, z0, args, max_steps=settings.max_steps, throw=False)
    empty = jnp.zeros(0, z0.dtype)
    return (to_x(sol.value), sol.result == optx.RESULTS.successful, sol.stats["num_steps"], jnp.sum(fn(sol.value, args) ** 2),
            empty, empty, empty)


def data_factor(r, J, args):
    """T, upper triangular (min(n, P + 1) x (P + 1)), of [J r] over the n data rows of a solve's r and J in z
    (`triangular`, by XLA's QR in the solver's program: ~0.16 ms for the Stanford arm's 1200 x 56 against ~0.5 ms
    on the host with its copies), when args["factor"] > 0 (traced; else zeros, not computed); (0, 0) for a solver
    that returns no J or arguments without "factor". `solver_residual_and_jacobian` takes it to x."""
    if not J.size or "factor" not in args:
        return jnp.zeros((0, 0), J.dtype)
    n = args["w"].size
    A = jnp.concatenate([J[:n], r[:n, None]], axis=1)
    k = min(A.shape)
    return jax.lax.cond(args["factor"] > 0, lambda: jnp.linalg.qr(A, mode="r")[:k], lambda: jnp.zeros((k, A.shape[1]), A.dtype))


@functools.partial(jax.jit, static_argnames=("model", "settings", "batched", "width"))
def _solve_jit(x0, args, limit, *, model, settings, batched, width=None):
    """One solve (x, converged, steps, cost, history, r, J: `_solve_one`, and T: `data_factor`), or a vmapped batch
    without r, J and T (their size grows with the batch): `batched` names the entries of args (and "x0") with a
    leading batch axis."""
    one = functools.partial(_solve_one, limit=limit, model=model, settings=settings, width=width)
    if not batched:
        out = one(x0, args)
        return (*out, data_factor(out[5], out[6], args))
    axes = {k: (0 if k in batched else None) for k in args}
    return jax.vmap(lambda x, a: one(x, a)[:5], (0 if "x0" in batched else None, axes))(x0, args)


def step_limit(n: int):
    """The iteration cap argument of a compiled solver (one dtype, so one executable)."""
    return np.asarray(n, np.int32)


# XLA options of the solver's program on CPU: XLA:CPU's elemental code generator instead of its MLIR fusion emitters.
# It compiles the solver 10-25 % faster, and its code runs as fast but for poses, ~10 % slower (this 2-core machine,
# fresh processes, alternating, 2026-11-27: Stanford arm 200 positions, first call 3.56, 3.79 -> 2.89, 2.96 s, warm
# 32.3, 30.4 vs 30.1, 31.9 ms; 200 poses first 4.53-5.03 -> 3.70-4.35 s, warm 52.0-74.6 vs 56.0-87.8 ms; real TALOS
# arm first 3.76, 3.62 -> 3.44, 3.27 s, warm 133, 124 vs 137, 115 ms; with the flag for every program, the Delta at
# 125 positions: first 21.9 -> 17.4 s, warm 8.22 vs 7.68 s). Other backends compile with their defaults.
CPU_COMPILE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
# And, for the solvers of open chains and of the Delta, no YNNPACK: jaxlib 0.10 hands every dot to that library
# (`xla_cpu_experimental_ynn_fusion_type` defaults to individual dots), a call of ~7 us however small the dot; 82 of
# them were a third of the Stanford arm's residual-and-Jacobian kernels (200 positions: 1.59 -> 1.36 ms without; XLA's
# own dots ~2.7 us each). The other closed mechanisms keep it (`Closure.xla_dots`): their closures' Newton solves
# differentiate in forward mode, and without it their programs compile 0.4-3.4 s longer (four-bars, Kiwibot) for
# 8-16 % less run time. Measured in docs/benchmarks.md ("YNNPACK", 2026-11-29; the Delta, thirteenth session).
XLA_DOTS_CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


def _model_robot(model):
    """The residual model's robot (`RobotDevice`'s, or a gap model's), or None."""
    return getattr(model, "robot", None) or getattr(getattr(model, "model", None), "robot", None)


def xla_dots(model) -> bool:
    """Whether the model's solver compiles with XLA's own dots (XLA_DOTS_CPU_OPTIONS): an open chain, or a closed
    mechanism whose closure says so (`Closure.xla_dots`)."""
    robot = _model_robot(model)
    return robot is None or robot.closure is None or robot.closure.xla_dots


def compile_solver(lowered, placed: bool, own_dots: bool = False):
    """`lowered.compile()` with CPU_COMPILE_OPTIONS (and XLA_DOTS_CPU_OPTIONS with own_dots: `xla_dots`) when the
    program runs on the default device of a CPU backend; where this jaxlib does not know an option, with fewer."""
    if not placed and jax.default_backend() == "cpu":
        tries = [CPU_COMPILE_OPTIONS | XLA_DOTS_CPU_OPTIONS] if own_dots else []
        for options in tries + [CPU_COMPILE_OPTIONS]:
            try:
                return lowered.compile(compiler_options=options)
            except Exception as error:  # jaxlib's JaxRuntimeError: INVALID_ARGUMENT: No such compile option
                if "No such compile option" not in str(error):
                    raise
    return lowered.compile()


_COMPILED: collections.OrderedDict = collections.OrderedDict()
_COMPILED_MAX = 64  # compiled solvers kept per process (least recently used first out)
compiled.register(_COMPILED.clear)


def compiled_model_solver(x0, args, model, settings: Settings, batched=(), width: int | None = None, compile: bool = True):
    """(executable, seconds spent compiling: 0 when reused), called as exe(x0, args, limit) with limit the cap
    on iterations (`step_limit`); width: the LM's step width (`Problem.step_width`; None: every column); with
    compile False, (None, 0.0) where the program is not compiled yet. One
    compile per residual model, settings, step width, argument shapes and placement (arrays
    committed to another JAX device get their own executable); at most _COMPILED_MAX are kept (robots hash by
    identity, so the cache is bounded). With a compilation-cache folder in use, the lowered program is kept
    there too (`jaxcal.exported`): a later process skips tracing it."""
    placed = exported.placements((x0, args))
    if not placed:  # arrays on the default device: the program of the sample count's bucket
        args = buckets.padded_solver_args(args, batched, zeros_placeholder)
    key = (model, settings, tuple(batched), exported.signature((x0, args)), placed, exported.lowering_config(), width)
    with _CACHE_LOCK:
        if key in _COMPILED:
            _COMPILED.move_to_end(key)
            return _on_bucket(_COMPILED[key], batched, placed), 0.0
    if not compile:
        return None, 0.0
    t = time.perf_counter()
    static = dict(model=model, settings=settings, batched=tuple(batched), width=width)
    if placed:  # committed to another device: lowered for that placement, not kept across processes
        exe = compile_solver(_solve_jit.lower(x0, args, step_limit(0), **static), True)
    else:
        exe = compile_solver(exported.lower(_solve_jit, (x0, args, step_limit(0)), static), False, xla_dots(model))
    with _CACHE_LOCK:
        _COMPILED[key] = exe
        if len(_COMPILED) > _COMPILED_MAX:
            _COMPILED.popitem(last=False)
    return _on_bucket(exe, batched, placed), time.perf_counter() - t


@dataclasses.dataclass(frozen=True)
class BucketedSolver:
    """A compiled solver built for a sample-count bucket, called as exe(x0, args, limit) with the arguments of any
    sample count in the bucket (`buckets.padded_solver_args`). Its r and J have the bucket's data rows, 0 past the
    caller's, then the prior rows: callers read the data rows as the first N*m."""

    exe: object
    batched: tuple

    def __call__(self, x0, args, limit):
        return self.exe(x0, buckets.padded_solver_args(args, self.batched, zeros_placeholder), limit)


def _on_bucket(exe, batched, placed):
    """exe as `BucketedSolver` for arguments on the default device; placed arguments (sharded over devices) keep their
    own shapes."""
    return exe if placed else BucketedSolver(exe, tuple(batched))


def evaluator(problem: "Problem", args, settings: Settings | None = None, compile: bool = True):
    """(executable, compile seconds) of the core LM solver for the problem's arguments `args`, which
    `Problem.jacobian` runs for 0 iterations to read the Jacobian: with `settings` when they select the core LM
    (so that the solves of `calibrate` share the program), else one already compiled for these shapes with any
    tolerances, else `Settings()`'s. compile False: (None, 0.0) where that program is not compiled yet."""
    x0 = np.zeros(len(problem.names))
    if settings is not None and isinstance(make_solver(settings.solver, settings.rtol, settings.atol), LevenbergMarquardt):
        return compiled_model_solver(x0, args, problem.model, settings, width=problem.step_width, compile=compile)
    shapes, config = exported.signature((x0, buckets.padded_solver_args(args, (), zeros_placeholder))), exported.lowering_config()
    with _CACHE_LOCK:
        kept = list(reversed(_COMPILED.items()))
    for key, exe in kept:
        model, done, batched, done_shapes, placed, done_config, width = key
        if (model == problem.model and not batched and done_shapes == shapes and not placed and done_config == config
                and width == problem.step_width and isinstance(make_solver(done.solver, done.rtol, done.atol), LevenbergMarquardt)):
            return BucketedSolver(exe, ()), 0.0
    return compiled_model_solver(x0, args, problem.model, Settings(), width=problem.step_width, compile=compile)


def compiled_solver(x0, args, robot, device, settings: Settings, batched=()):
    """`compiled_model_solver` of the robot measured by the device."""
    return compiled_model_solver(x0, args, RobotDevice(robot, device), settings, batched)


@functools.partial(jax.jit, static_argnums=(0,))
def _model_rows(model, x, q, y, cov, w):
    return model.residuals(x, q, y, cov, w)


def per_sample(w, n: int) -> np.ndarray:
    """Weights (m,) of every sample as the (n, m) array (float64, not weak-typed): one argument shape for
    the compiled residuals and Jacobian whether a caller passes per-component or per-sample weights (on the
    Delta, the second compile of the residuals cost ~11 s)."""
    w = np.asarray(w, float)
    return np.broadcast_to(w, (n, w.shape[0])) if w.ndim == 1 else w


def model_residuals(model, x, q, y, cov, w) -> np.ndarray:
    """The residual model's weighted residuals (N, m) at x, as a numpy array. The robot measured by a device
    runs its own compiled parts (`residuals`); another model is compiled whole."""
    x, q, y, cov, w = (np.asarray(v, float) for v in (x, q, y, cov, per_sample(w, len(q))))
    n = len(q)
    size, row = buckets.sample_bucket(n), buckets.row_in_use(w)  # one program per bucket of sample counts
    y, cov, w_bucket = buckets.repeat_row(y, size, row), buckets.repeat_row(cov, size, row), buckets.zero_rows(w, size)
    if isinstance(model, RobotDevice):  # the readings shared with the registration and predictions (`predicted`)
        read = buckets.repeat_row(predicted(model.robot, model.device, x, q), size, row)
        return np.asarray(misfit(model.device, read, y, w_bucket))[:n]
    return np.asarray(_model_rows(model, x, buckets.repeat_row(q, size, row), y, cov, w_bucket))[:n]


def no_covariates(n: int) -> np.ndarray:
    """The (N, 0) covariate matrix of a model that takes none."""
    return np.zeros((n, 0))


def weighted_residuals(robot, device, a_full, q, y, w) -> np.ndarray:
    """w * (y - read(a_full, q)) as a numpy array (N, m)."""
    return model_residuals(RobotDevice(robot, device), a_full, q, y, no_covariates(len(q)), w)


def jacobian(robot, device, a_full, q, y, w) -> np.ndarray:
    """d(weighted residual)/d(a_full), (N*m, P) (`Problem.jacobian`)."""
    P = len(robot.names) + len(device.names)
    free, no_bound = np.ones(P, bool), np.full(P, np.inf)
    return Problem(robot, device, np.asarray(q, float), np.asarray(y, float), per_sample(w, len(q)), free,
                   np.asarray(a_full, float), -no_bound, no_bound).jacobian(a_full)


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A calibration problem: robot, device, data, weights and what is estimated.

    q (N, n_inputs), y (N, *reading_shape); w (N, m) the weight 1/sigma of every residual component
    times the sample weight (0 removes a sample); free: mask over the full vector of what may be
    estimated; a_ref: the prior (full vector); bounds lb, ub (full vector, +-inf where none);
    cov (N, c): per-sample covariates of the residual model (N, 0 when it takes none); model: the
    residual model (default `RobotDevice(robot, device)`; the gap refits give their `GapModel`, whose
    full vector appends effect parameters to the robot's and the device's).
    """

    robot: Robot
    device: Device
    q: np.ndarray
    y: np.ndarray
    w: np.ndarray
    free: np.ndarray
    a_ref: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    cov: np.ndarray | None = None
    model: object = None

    def __post_init__(self):
        if self.model is None:
            object.__setattr__(self, "model", RobotDevice(self.robot, self.device))
        if self.cov is None:
            object.__setattr__(self, "cov", no_covariates(len(self.q)))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.model.names)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(self.model.units)

    @property
    def priority(self) -> np.ndarray:
        return np.asarray(self.model.priority)

    @property
    def x_scale(self) -> np.ndarray:
        """Typical size of a change of each entry of the full vector (the solver's unit in z)."""
        return np.asarray(self.model.x_scale(), float)

    @property
    def used(self) -> np.ndarray:
        """Samples with a non-zero weight."""
        return np.any(self.w != 0, axis=1)

    def with_weights(self, w) -> "Problem":
        return dataclasses.replace(self, w=np.asarray(w, float))

    def residuals(self, x) -> np.ndarray:
        """Weighted residuals (N, m) at the full vector x."""
        return model_residuals(self.model, x, self.q, self.y, self.cov, self.w)

    @functools.cached_property
    def prior_residuals(self) -> np.ndarray:
        """The weighted residuals (N, m) at the prior a_ref, evaluated once: `start` compares the registered frame's
        cost with theirs, and `identify` reports the nominal model's RMS from them."""
        return self.residuals(self.a_ref)

    def jacobian(self, x, columns=None) -> np.ndarray:
        """d(weighted residual)/dx (N*m, P) at the full vector x (`residual_and_jacobian`)."""
        return self.residual_and_jacobian(x, columns)[1]

    def residual_and_jacobian(self, x, columns=None) -> tuple[np.ndarray, np.ndarray]:
        """(weighted residuals (N, m), d(weighted residual)/dx (N*m, P)) at the full vector x: the data rows that the
        solver's executable (`evaluator`) returns after 0 iterations from x, every entry estimated at unit scale (the
        reverse-mode data Jacobian of `data_residual_and_jacobian` for open chains, forward mode through closures).
        One compiled program for the solves and the Jacobian: on the Delta the Jacobian compiled apart took ~7 s.
        columns: the indices whose columns are needed (default every one); where none is the robot's, the robot's
        columns are returned as 0 (`holds_robot`: the kinematics are not differentiated). A solve from x takes the
        pair as its `start`."""
        return self.read(x, columns)[:2]

    def read(self, x, columns=None, factor: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """`residual_and_jacobian` and, with factor, the triangular factor T of the data rows' [J r] at x
        (`triangular`, computed in the same program: `data_factor`; else None)."""
        P = len(self.names)
        mask = np.ones(P)
        if columns is not None:
            mask = np.zeros(P)
            mask[np.asarray(columns, int)] = 1.0
        args = self.solver_arrays(x, mask, self.w, 0.0, np.ones(P), factor=factor)
        exe, _ = evaluator(self, args)
        r, J, T = exe(np.asarray(x, np.float64), args, step_limit(0))[5:]
        n = self.w.size
        return np.asarray(r)[:n].reshape(self.w.shape), np.asarray(J)[:n], (np.asarray(T) if factor else None)

    def solver_arrays(self, ref, mask, w, mu, scale, start=None, stop: float = 0.0, factor: bool = False,
                      full: bool = False) -> dict:
        """The solver's arguments: prior ref (P,), estimated mask (P,), data weights w (N, m), bias mu (a number or
        (P,)), unit of z per entry scale (P,) (`stacked_scaled`), with the problem's data and bounds. start: the data
        rows' (r (N, m), J (N*m, P)) at ref with the weights w, which the solve then does not evaluate again
        (`given_start`); without it, placeholders of the same shapes (one program either way). stop: the core LM's
        relative decrease that ends a start (`lm.advance`; 0: none). factor: the program returns the triangular factor
        of the data rows' [J r] at its end too (`data_factor`). full: J has the robot's columns even where no robot
        entry is estimated (else they are 0 there, `holds_robot`)."""
        f64 = functools.partial(np.asarray, dtype=np.float64)  # numpy: a compiled call takes them as they are
        n, P = self.w.size, len(self.names)
        r0, J0 = (zeros_placeholder((n,)), zeros_placeholder((n, P))) if start is None else (f64(start[0]).reshape(n), f64(start[1]))
        return dict(a_ref=f64(ref), mask=f64(mask), q=f64(self.q), y=f64(self.y), cov=f64(self.cov), w=f64(w), mu=f64(mu),
                    x_scale=f64(scale), lb=f64(self.lb), ub=f64(self.ub),
                    start=dict(r=r0, J=J0, given=f64(start is not None)), stop=f64(stop), factor=f64(factor), full=f64(full))

    def args(self, estimated, mu, ref, start=None, ref_residuals=None, stop: float = 0.0, factor: bool = False,
             full: bool = False) -> dict:
        """Solver arguments: estimate the indices `estimated`, bias mu (a number, or one per entry) toward
        `ref`. The data weights are divided by the RMS weighted residual over the used samples at `ref`: the
        optimum is unchanged and LM starts with an O(1) residual (optimistix's trust region took 4 to 34
        iterations on the same problem depending on that scale); samples of weight 0 do not enter that RMS,
        so a fold (weight mask) and the subset it selects see the same scaled problem. start: the solve's (r, J) at
        its x0 (`residual_and_jacobian`), scaled alike for the solver (`solver_arrays`); ref_residuals: the weighted
        residuals at ref when the caller has them (else evaluated here); stop, factor, full: `solver_arrays`'."""
        mask = np.zeros(len(self.names))
        mask[np.asarray(estimated, int)] = 1.0
        r = self.residuals(ref) if ref_residuals is None else np.asarray(ref_residuals)
        used = self.used
        rms = max(np.sqrt(np.sum(r[used] ** 2) / max(r[used].size, 1)) if used.any() else 1.0, 1e-12)
        scaled = None if start is None else (np.asarray(start[0]) / rms, np.asarray(start[1]) / rms)
        return self.solver_arrays(ref, mask, self.w / rms, mu, self.x_scale, scaled, stop, factor, full)

    def batch_args(self, estimated, mu, refs, weights) -> dict:
        """Arguments of a batch of solves of this problem that differ in their prior refs (B, P) and data
        weights (B, N, m) (folds as weight masks), each scaled as `args` scales one; "a_ref" and "w" carry the
        batch axis (`solve_batch(..., batched=("x0", "a_ref", "w"))`)."""
        each = [self.with_weights(w).args(estimated, mu, ref) for ref, w in zip(refs, weights)]
        return dict(each[0], a_ref=jnp.stack([a["a_ref"] for a in each]), w=jnp.stack([a["w"] for a in each]))

    def basis_args(self, columns, K: int, mu, refs, weights) -> dict:
        """`batch_args` for a solve in the basis S (P, K) that moves the entries `columns` at their typical size
        (`stacked_basis`; K >= len(columns), the rest padding), mu a number or one per column."""
        S = np.zeros((len(self.names), K))
        cols = np.asarray(columns, int)
        S[cols, np.arange(len(cols))] = self.x_scale[cols]
        mask = (np.arange(K) < len(cols)).astype(float)
        mu_k = np.zeros(K)
        mu_k[:len(cols)] = mu
        args = self.batch_args(cols, 0.0, refs, weights)
        return dict(args, S=jnp.asarray(S), mask=jnp.asarray(mask), mu=jnp.asarray(mu_k))

    @property
    def step_width(self) -> int | None:
        """The core LM's step width for this problem's solves (`lm.step_columns`): the entries the robot frees by
        default (`Robot.free_mask`) and the device's, rounded up to a multiple of STEP_WIDTH_ROUND, when that leaves
        out at least a third of the columns (closed mechanisms: the Delta frees 83 of 166, the Kiwibot 48 of 94), else
        None (every column, the others masked). A property of the robot and device, not of the call's free entries:
        every solve and Jacobian read of the pair (the frames-only fits of `free=()` too) shares one program."""
        if not isinstance(self.model, RobotDevice):
            return None
        n_free, P = int(np.sum(self.robot.free_mask)) + self.device.n_params, len(self.names)
        width = -(-n_free // STEP_WIDTH_ROUND) * STEP_WIDTH_ROUND
        return width if 0 < width and 3 * width <= 2 * P else None

    def width_for(self, mask) -> int | None:
        """`step_width` when it holds every entry the mask (P,) or masks (B, P) estimate, else None."""
        width = self.step_width
        most = int(np.max(np.sum(np.atleast_2d(np.asarray(mask)) > 0, axis=-1)))
        return width if width is not None and most <= width else None

    def holds_robot(self, mask, full: bool = False) -> bool:
        """The solver's Jacobian for the estimated mask (P,) leaves the robot's columns 0: no robot entry is estimated,
        the columns are not all asked for (`solver_arrays`' full) and the model is the robot measured by a device
        (`RobotDevice.residual_and_jacobian`'s robot_held)."""
        return (isinstance(self.model, RobotDevice) and jacobian_mode(self.model) == "reverse" and not full
                and not np.any(np.asarray(mask)[:self.robot.n_params] > 0))

    def cost(self, a_full) -> float:
        return float(np.sum(self.residuals(a_full) ** 2))


PLACEHOLDER_KEPT = 1 << 21  # entries (16 MB): larger placeholders are made for each call, not kept


@functools.lru_cache(maxsize=4)
def _kept_zeros(shape: tuple) -> jax.Array:
    return jax.device_put(np.zeros(shape))


compiled.register(_kept_zeros.cache_clear)


def zeros_placeholder(shape: tuple):
    """Zeros of the shape for an argument that the solver's program reads only when told to (`Problem.solver_arrays`'
    start): kept on the default device for the last few shapes up to PLACEHOLDER_KEPT entries, so that a call does not
    make and copy them (Stanford arm, 200 poses: 0.1-0.17 ms of a 1.5 ms Jacobian read)."""
    return _kept_zeros(shape) if int(np.prod(shape)) <= PLACEHOLDER_KEPT else np.zeros(shape)


def make_problem(robot: Robot, device: Device, q, y, *, weights, free, a_ref, bounds=None, sample_weights=None,
                 model=None, cov=None) -> Problem:
    """A `Problem`: weights (m,) per residual component, optionally times sample_weights (N,); model and cov
    (N, c): a residual model other than the robot measured by the device, and its per-sample covariates."""
    device.check_robot(robot)
    if robot.closure is not None and model is None:  # a closure whose shortcut the free entries would break: the general one
        robot = robot.closure.serving(robot, np.asarray(a_ref, float)[:robot.n_params], np.asarray(free, bool)[:robot.n_params])
    q, y = np.asarray(q, float), np.asarray(y, float)
    w = np.broadcast_to(np.asarray(weights, float), (len(q), np.size(weights))).copy()
    if sample_weights is not None:
        sw = np.asarray(sample_weights, float)
        if sw.shape != (len(q),) or not np.all(np.isfinite(sw)) or np.any(sw < 0):
            raise ValueError(f"sample_weights must be {len(q)} finite non-negative numbers")
        w = sw[:, None] * w
    names = tuple((RobotDevice(robot, device) if model is None else model).names)
    lb, ub = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    check_names(list(bounds or {}), names, "bounds: parameter")  # UnknownNameError (a KeyError), closest names named
    for n, (lo, hi) in (bounds or {}).items():
        lb[names.index(n)], ub[names.index(n)] = lo, hi
    return Problem(robot, device, q, y, w, np.asarray(free, bool), np.asarray(a_ref, float), lb, ub,
                   None if cov is None else np.asarray(cov, float), model)


# -- the start ------------------------------------------------------------------------------------
def similarity_registration(P, Y):
    """(s, R, t) minimising sum_i |s R y_i + t - p_i|^2 over rotations R, scales s > 0 and t (Umeyama 1991:
    SVD of the centred cross-covariance with the sign fix that excludes reflections)."""
    pc, yc = P.mean(axis=0), Y.mean(axis=0)
    U, S, Vt = np.linalg.svd((Y - yc).T @ (P - pc))
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    var_y = np.sum((Y - yc) ** 2)
    s = float((S[0] + S[1] + d * S[2]) / var_y) if var_y > 0 else 1.0
    return s, R, pc - s * R @ yc


def rigid_registration(P, Y):
    """(R, t) minimising sum_i |R y_i + t - p_i|^2 over rotations (Kabsch; Arun, Huang & Blostein 1987)."""
    _, R, _ = similarity_registration(P, Y)
    return R, P.mean(axis=0) - R @ Y.mean(axis=0)


def _unit_mistake(scale: float) -> str | None:
    """The length unit the readings seem to be in, when the registration scale says they are not in metres."""
    for unit, s in UNIT_SCALES.items():
        if abs(np.log(scale / s)) < np.log(1.25):
            return unit
    return None


def registered_frame(problem: Problem, a_full) -> np.ndarray | None:
    """a_full with each device frame D (readings y = D^-1 p; one per session, `Device.frame_blocks`) set by rigid
    registration of its samples' readings onto the model's points p at a_full (marker offset as given). None when
    the device has no free 6-D frame, its readings carry no points, or no frame's points span a plane.
    Raises DataError when the readings fit the model only after scaling by 1/1000 (mm), 1/100 (cm) or 1/25.4."""
    device, robot = problem.device, problem.robot
    used = problem.used
    blocks = [(np.asarray(idx), mask[used]) for idx, mask in device.frame_blocks(problem.y)
              if np.all(problem.free[robot.n_params + np.asarray(idx)])]
    Y_all = device.points(problem.y[used])
    if not blocks or Y_all is None:
        return None
    x = np.array(a_full, float)
    for idx, _ in blocks:
        x[robot.n_params + idx] = 0.0  # identity frames: the readings are then the model's points
    pred = predicted(robot, device, x, problem.q)[used]  # the fits' shape: one compile
    P_all = device.predicted_points(pred)
    registered = False
    for idx, mask in blocks:
        frame = _registration(device, P_all[mask].reshape(-1, 3), Y_all[mask].reshape(-1, 3))
        if frame is not None:
            x[robot.n_params + idx] = frame
            registered = True
    return x if registered else None


UNIT_FIT = 0.2  # a scaled registration names a unit mistake only when its residual is below this share of the spread


def _explains(P, P_fit) -> bool:
    """The registered points P_fit explain P: RMS misfit below UNIT_FIT x the RMS spread of P. Readings taken in
    several frames (sessions mixed up) also register best at a small scale, but do not fit."""
    spread = np.sqrt(np.mean(np.sum((P - P.mean(0)) ** 2, axis=1)))
    return bool(np.sqrt(np.mean(np.sum((P - P_fit) ** 2, axis=1))) < UNIT_FIT * spread)


def _registration(device: Device, P, Y) -> np.ndarray | None:
    """(x, y, z, rx, ry, rz) of the frame D with P = D Y (rigid registration), or None for fewer than 3 finite
    points or points on a line; DataError when a similarity fits only with a length-unit scale."""
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Y), axis=1)
    P, Y = P[ok], Y[ok]
    if len(P) < 3 or np.linalg.svd(Y - Y.mean(0), compute_uv=False)[1] < 1e-9 * max(np.ptp(Y), 1e-300):
        return None
    s, R, t = similarity_registration(P, Y)
    unit = _unit_mistake(s)
    if unit is not None and _explains(P, s * Y @ R.T + t):
        raise DataError(f"the {device.kind} readings fit the robot only after scaling them by {s:.4g}: they look like {unit}, "
                        "not metres; give the unit (Dataset.from_csv(..., length_unit=...) or a '# units:' line)")
    from scipy.spatial.transform import Rotation  # on the host: a compiled log_so3 took 0.13 s of the first call

    # the rigid fit (`rigid_registration`) has the similarity's rotation, which does not depend on the scale
    return np.concatenate([P.mean(axis=0) - R @ Y.mean(axis=0), Rotation.from_matrix(R).as_rotvec()])


@dataclasses.dataclass(frozen=True)
class Solution:
    """One solver run: the full vector, whether the solver met its tolerance, its steps and final cost; history:
    the cost at the start and after each step (the core's LM; empty for the optimistix solvers); estimated: the
    indices it moved; J: the data rows' Jacobian at x, every column (`Problem.jacobian`), read off the core's LM
    (None for the other solvers, for a batch, and for a fit of device parameters alone: `Problem.holds_robot`); r:
    the weighted residuals (N, m) at x that come with J (`Problem.residual_and_jacobian`; None where J is); factor: the
    triangular factor of [J r] (`triangular`) when the solve was asked for it (`data_factor`), else None."""

    x: np.ndarray
    converged: bool
    steps: int
    cost: float
    compile_s: float
    history: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    estimated: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))
    J: np.ndarray | None = None
    r: np.ndarray | None = None
    factor: np.ndarray | None = None

    @property
    def read(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(r, J) at x, the `start` of a solve from x (None without J)."""
        return None if self.J is None else (self.r, self.J)


def solver_residual_and_jacobian(problem: Problem, r_z, J_z, args, T_z=None) -> tuple | None:
    """(r, J, T): `Problem.read` at a solve's end from the residual, Jacobian and factor that the core's LM returns
    there (in z, with the data weights that `Problem.args` scaled): the data rows, times the weights' scale
    w / args["w"] (one number), J's columns divided by their x_scale, T's alike (R of [J r] D is R D for a positive
    diagonal D; T_z None: T None). None when the solver returned no J (the optimistix solvers)."""
    J_z = np.asarray(J_z)
    if not J_z.size:
        return None
    w, w_solver = problem.w, np.asarray(args["w"])
    used = w != 0
    weight_scale = float(np.median(w[used] / w_solver[used])) if used.any() else 1.0
    r = (np.asarray(r_z)[:w.size] * weight_scale).reshape(w.shape)
    J = J_z[:w.size] / np.asarray(args["x_scale"]) * weight_scale
    T = None if T_z is None else np.asarray(T_z) * (np.append(1.0 / np.asarray(args["x_scale"]), 1.0) * weight_scale)
    return r, J, T


def reweighted(read, w_from, w_to) -> tuple[np.ndarray, np.ndarray] | None:
    """(r, J) at one point for the data weights w_to (N, m) from (r, J) for w_from (each row is its weight times an
    unweighted row): a fold's start from the whole problem's. None when w_to weights a row that w_from removed."""
    if read is None or np.any((w_from == 0) & (w_to != 0)):
        return None
    ratio = np.divide(w_to, w_from, out=np.zeros(np.shape(w_to)), where=w_from != 0)
    return read[0] * ratio, read[1] * ratio.reshape(-1, 1)


def solve(problem: Problem, x0, estimated, settings: Settings, mu: float = 0.0, ref=None, limit: int | None = None,
          start=None, ref_residuals=None, stop: float = 0.0, factor: bool = False, full: bool = False) -> Solution:
    """Minimise the stacked residual over the `estimated` indices from x0, with bias mu toward ref (default x0);
    limit: at most this many iterations (default settings.max_steps; the same compiled program). start: (r, J) at
    x0 (`Problem.residual_and_jacobian`, `Solution.read`; with the robot's columns 0 only for a solve that holds
    the robot), which the solver then does not evaluate again; x0 must then agree with ref on the entries not
    estimated (the solver holds those at ref). ref_residuals: the problem's weighted residuals (N, m) at ref when the
    caller has them (`Problem.args`' scale; else evaluated there, unless start is at ref). stop: for the core's LM, a
    step predicted to lower the cost by at most this share of it ends the solve, converged (a start: START_STOP).
    factor: the solution carries the triangular factor of [J r] at x (`Solution.factor`), where it carries J.
    full: the solve's Jacobian has the robot's columns, and the solution carries J, even where no robot entry is
    estimated (`Problem.holds_robot`); its start, if given, must have them too."""
    x0 = np.asarray(x0, np.float64)
    ref = x0 if ref is None else np.asarray(ref, np.float64)
    mask = np.zeros(len(x0), bool)
    mask[np.asarray(estimated, int)] = True
    if start is not None and not np.array_equal(np.where(mask, x0, ref), x0):
        raise ValueError("solve: a start (r, J) is at x0, which must agree with ref on the entries not estimated")
    at_ref = start is not None and np.array_equal(x0, ref)
    args = problem.args(estimated, mu, ref, start, start[0] if at_ref else ref_residuals, stop, factor, full)
    exe, dt = compiled_model_solver(x0, args, problem.model, settings, width=problem.width_for(args["mask"]))
    cap = settings.max_steps if limit is None else min(limit, settings.max_steps)
    x, ok, steps, cost, history, r_z, J_z, T_z = exe(x0, args, step_limit(cap))
    x = np.where(np.asarray(args["mask"]) > 0, np.asarray(x), np.asarray(ref))
    history = np.asarray(history)
    read = (None if problem.holds_robot(args["mask"], full)  # the robot's columns 0
            else solver_residual_and_jacobian(problem, r_z, J_z, args, T_z if factor else None))
    r, J, T = (None, None, None) if read is None else read
    return Solution(x, bool(ok), int(steps), float(cost), dt, history[np.isfinite(history)], np.asarray(estimated, int), J, r, T)


def solve_batch(problem: Problem, x0s, args, settings: Settings, batched, limit: int | None = None) -> tuple:
    """A vmapped batch of solves of one problem's structure: `batched` names the leading-axis entries of
    args (and "x0" for a batch of starts; `Problem.batch_args` for folds with their own priors); limit: at most this
    many iterations (default settings.max_steps; the same compiled program).
    Returns (x (B, P), ok (B,), steps (B,), cost (B,), compile_s)."""
    exe, dt = compiled_model_solver(x0s, args, problem.model, settings, batched, problem.width_for(args["mask"]))
    cap = settings.max_steps if limit is None else min(limit, settings.max_steps)
    x, ok, steps, cost, _ = exe(x0s, args, step_limit(cap))
    return np.asarray(x), np.asarray(ok), np.asarray(steps), np.asarray(cost), dt


def free_device_entries(problem: Problem) -> np.ndarray:
    """Indices (into the full vector) of the device parameters the problem may estimate."""
    nr = problem.robot.n_params
    return np.flatnonzero(problem.free[nr:]) + nr


def frames_estimated(problem: Problem, x, J=None) -> np.ndarray:
    """Indices of the device parameters the frames-only fit estimates at x: the base set (device priorities) of
    the free device columns of the Jacobian in typical-size units, at the relative pivot tolerance START_TOL.
    J: the Jacobian at x with at least those columns, when the caller has it (else it is read here).

    With the robot at its prior, the readings carry the robot's own errors; a device parameter whose column
    lies within START_TOL of the span of the others would absorb them amplified ~1/pivot (a Delta's platform
    barely turns, so its tool offset and the tracker's position differ by pivots of ~1e-6: 1 mm of geometry
    error put both ~300 m away). Those parameters stay at their prior until the full fit, whose base set
    decides them with the geometry."""
    cand = free_device_entries(problem)
    if not cand.size:
        return cand
    J = (problem.jacobian(x, cand) if J is None else J)[:, cand]
    bs = base_set(J * problem.x_scale[cand], problem.priority[cand], c=START_TOL / np.finfo(float).eps)
    return np.sort(cand[bs.independent])


def offset_stop(problem: Problem, unknowns: int) -> float:
    """The `stop` (share of the cost, `lm.advance`) of Bates and Watts' relative offset criterion for a fit of
    `unknowns` parameters to the problem's used readings: OFFSET_TOL^2 p / (readings - p); 0 (none) without
    degrees of freedom."""
    dof = int(np.sum(problem.w != 0)) - unknowns
    return OFFSET_TOL**2 * unknowns / dof if dof > 0 else 0.0


def start(problem: Problem, settings: Settings, full: bool = False, factor: bool = False) -> tuple[np.ndarray, Solution | None, bool]:
    """The one start: the device frame registered onto the nominal model (where that lowers the cost), then
    the device parameters the nominal model can determine (`frames_estimated`) fitted with the robot at its
    prior. Returns (x, frames-only solution, registered).
    full: the frames-only solution carries J with every column at its end (`solve`'s full), and with factor its
    triangular factor: the next fit's start and base set without a Jacobian read of their own. Its evaluations
    then differentiate the kinematics too (Stanford arm, 200 poses: a Jacobian read 0.70 -> 0.91 ms), which one
    read less repays (1.41 ms with the factor)."""
    x = np.array(problem.a_ref, float)
    reg = registered_frame(problem, x)
    cand = free_device_entries(problem)  # a registered frame is free: not empty then
    columns = None if full else cand
    # J at the start (the device's columns; every column with full): the frames solve's start; at the registered frame
    # its residuals decide too
    read = None if reg is None else problem.residual_and_jacobian(reg, columns)
    registered = read is not None and float(np.sum(np.square(read[0]))) < float(np.sum(np.square(problem.prior_residuals)))
    if registered:
        x = reg
    elif cand.size:
        read = problem.residual_and_jacobian(x, columns)
    dev_idx = frames_estimated(problem, x, None if read is None else read[1])
    if not dev_idx.size:
        return x, None, registered
    sol = solve(problem, x, dev_idx, settings, start=read, stop=START_STOP, factor=factor, full=full)
    return sol.x, sol, registered


def residuals_in_background(problem: Problem) -> threading.Thread:
    """A started thread that evaluates the residuals at the prior (`Problem.residuals`, whose readings
    `predicted` keeps), the start's first evaluation: their programs compile while the solver's does (XLA
    compiles outside the GIL). An error there is left to the start, which evaluates the same point again."""

    def evaluate():
        with contextlib.suppress(Exception):
            problem.residuals(problem.a_ref)

    thread = threading.Thread(target=evaluate, name="jaxcal-prior-residuals", daemon=True)
    thread.start()
    return thread


# -- the whole calibration ------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Calibration:
    """What `calibrate` returns: the estimate and everything needed to judge it.

    x: full vector (robot, device); x_frames: the start (nominal robot, frames fitted); estimated /
    undetermined / no_effect / regrouped: index arrays into the full vector; J: weighted Jacobian at x
    (all columns); converged: every solver stage met its tolerance; iterations: steps of the last stage
    set; registered: the device frame came from the rigid registration; history: the solver's cost at the start
    and after each step of every bias stage (the core's LM without multi-start; else empty); frames_fitted: the
    device parameters the start fitted (with the robot at its prior), some of which the main fit may hold
    (`undetermined`) at those fitted values; polish: the final all-parameter stage (`polish`); stopped_early: the
    unbiased fit was stopped unconverged by `calibrate`'s early_stop."""

    problem: Problem
    x: np.ndarray
    x_frames: np.ndarray
    estimated: np.ndarray
    undetermined: np.ndarray
    no_effect: np.ndarray
    regrouped: np.ndarray
    J: np.ndarray
    converged: bool
    frames_converged: bool
    iterations: int
    registered: bool
    compile_s: float
    run_s: float
    history: np.ndarray
    J0: np.ndarray  # weighted Jacobian at x_frames (the base set's)
    frames_fitted: np.ndarray
    polish: dict  # the final all-parameter stage: tried, accepted, F ratio, costs (`polish`)
    stopped_early: bool = False  # the unbiased fit was stopped by `early_stop` (x, J: where it stopped; no polish)
    r0: np.ndarray | None = None  # weighted residuals (N, m) at x_frames, with J0 the first stage's start
    r: np.ndarray | None = None  # weighted residuals (N, m) at x that the last solve returned with J (None: not returned)
    factor: np.ndarray | None = None  # J's triangular factor when `calibrate` has it (`R`)
    factor0: np.ndarray | None = None  # the triangular factor of [J0 r0] when the start read it (`choose_estimated`)

    @functools.cached_property
    def residuals(self) -> np.ndarray:
        """The weighted residuals (N, m) at x: those the last solve returned with J, else evaluated once (`Problem.residuals`).
        The health checks, the bias rule and the covariance all read them."""
        return self.problem.residuals(self.x) if self.r is None else self.r

    @functools.cached_property
    def R(self) -> np.ndarray:
        """J's triangular factor (`triangular`): what the covariance, the weak directions, the conditioning and the
        standard errors of any columns of J need, at the cost of one QR instead of one SVD or product of J each. The
        final stage's F test factors [J r] (`polish`), whose leading block is J's: then that one."""
        return triangular(self.J) if self.factor is None else self.factor


def choose_estimated(problem: Problem, J, base: bool, base_tol: float | None, factor=None):
    """(estimated, undetermined, no_effect, regrouped) index arrays: the base set (seed 001 App. III) of the free
    columns of J under the priorities (pivot threshold base_tol, default BASE_TOL, relative to the largest),
    or every free column when base is False. factor: J's triangular factor (`triangular`; of [J r] too) when the
    caller has it: J = Q R with Q's columns orthonormal, so the columns of R have J's norms and QR pivots, and
    the base set is found on its P rows instead of J's N m."""
    cand = np.flatnonzero(problem.free)
    if not base:
        e = np.zeros(0, int)
        return cand, e, e, e
    c = (BASE_TOL if base_tol is None else base_tol) / np.finfo(float).eps
    bs = base_set((J if factor is None else factor)[:, cand], problem.priority[cand], c=c)
    return (np.sort(cand[bs.independent]), np.sort(cand[np.concatenate([bs.regrouped, bs.no_effect])]),
            cand[bs.no_effect], cand[bs.regrouped])


def bias_schedule(bias) -> list[float]:
    """mu per stage (seed 004 eq 3.12): none -> [0]; a number b -> b, b/10, b/100, b/1000, 0; a sequence as given."""
    if bias is None:
        return [0.0]
    if np.ndim(bias):
        return [float(b) for b in bias]
    return [float(bias) * 10.0**-k for k in range(4)] + [0.0]


def triangular(J, r=None) -> np.ndarray:
    """R, upper triangular (min(n, P) x P), with R = Q^T J for an orthogonal Q: R^T R = J^T J, so any columns of R have
    the singular values and right singular vectors of J's, and a least-squares problem min |J_S delta + J_k|^2 on
    columns of J has R's solution and residual (R of [J r] for one with a right-hand side r, given as r (n,) or
    (N, m)), whatever J's rank (`base.upper_factor`; Stanford arm, 200 poses, [J r] 1200 x 56: ~0.4 ms; an SVD of J
    2.2 ms, lstsq 1.3 ms, this 2-core CPU)."""
    J = np.asarray(J, float)
    if r is None:
        return upper_factor(J)
    A = np.empty((J.shape[0], J.shape[1] + 1), order="F")  # [J r] in column-major order: factored in place
    A[:, :-1], A[:, -1] = J, np.reshape(r, -1)
    return upper_factor(A, overwrite=True)


def f_ratio(cost_before: float, cost_after: float, k: int, dof: int) -> float:
    """F = ((C0 - C1) / k) / (C1 / dof): the cost drop per added parameter over the residual variance after."""
    return float((cost_before - cost_after) / k / max(cost_after / dof, 1e-300))


def linear_f_ratio(r, J, estimated, added, dof: int, factor=None) -> float:
    """`f_ratio` that one Gauss-Newton step predicts for adding the columns `added` to `estimated` at a point where
    the `estimated` ones are already fitted: C0 = |r|^2, C1 = min over all of them of |r + J delta|^2 (columns
    scaled to unit norm, so that the least-squares cut-off treats metres, radians and gains alike), solved on the
    triangular factor T of [J r] (`triangular`; [J r] = Q T with Q's columns orthonormal, so the columns' problem
    and their norms are T's, on P + 1 rows instead of J's). factor: that T, when the caller has it."""
    T = triangular(J, r) if factor is None else factor
    A, b = T[:, np.concatenate([estimated, added])], T[:, -1]
    A = A / np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    delta = small_lstsq(A, -b)
    c1 = float(np.sum((b + A @ delta) ** 2))
    return f_ratio(float(b @ b), c1, len(added), dof)


def polish(problem: Problem, x, J, estimated, undetermined, settings: Settings, r=None,
           factor=None) -> tuple[Solution | None, dict]:
    """The final stage: every free parameter with an effect at x, biased (POLISH_BIAS) toward the base-set estimate x.

    The base set is chosen at the start, where the held parameters' columns depend on the others; at the
    solution they may not, and holding them leaves a systematic residual. A column that was zero at the start
    (no effect there) may have one at x: those are added too (the 3-D four-bar with Table 4.2b's errors, noise
    free: 4 added -> 0.045 mm left; 9 added -> 0.0028 mm, measured). J: the weighted Jacobian at x. The
    stage is tried only when one Gauss-Newton step predicts an F ratio (`f_ratio`, k = the parameters added,
    dof = readings - all parameters) above POLISH_F, and kept only when the solve's own F ratio is above it
    too: fitting noise alone gives F ~ 1. r: the weighted residuals (N, m) at x that come with J (the solve's start;
    evaluated here when not given); factor: the triangular factor of [J r] when the caller has it (`linear_f_ratio`).
    Returns (solution or None, record)."""
    col = np.linalg.norm(J * problem.x_scale, axis=0)  # typical-size units
    effect = np.flatnonzero(col > NO_EFFECT_AT_SOLUTION * col.max())
    added = np.intersect1d(undetermined, effect)  # what has an effect at x (a column zero at the start may not be)
    dof = int(np.sum(problem.w != 0)) - len(estimated) - len(added)
    if not added.size or dof <= 0:
        return None, {"tried": False}
    r = problem.residuals(x) if r is None else r
    predicted = linear_f_ratio(r.reshape(-1), J, estimated, added, dof, factor)
    if not predicted > POLISH_F:
        return None, {"tried": False, "predicted_f_ratio": predicted}
    unknowns = np.sort(np.concatenate([estimated, added]))
    sol = solve(problem, x, unknowns, settings, mu=POLISH_BIAS, ref=x, start=(r, J), stop=offset_stop(problem, len(unknowns)),
                factor=True)
    c0, c1 = float(np.sum(np.square(r))), (problem.cost(sol.x) if sol.r is None else float(np.sum(np.square(sol.r))))
    f = f_ratio(c0, c1, len(added), dof) if np.isfinite(c1) else -np.inf
    record = {"tried": True, "accepted": bool(f > POLISH_F and sol.converged), "predicted_f_ratio": predicted,
              "f_ratio": f, "cost_before": c0, "cost_after": c1, "added": len(added), "added_index": added.tolist(),
              "steps": sol.steps}
    return (sol if record["accepted"] else None), record


def calibrate(problem: Problem, settings: Settings = Settings(), *, base: bool = True, bias=None, multistart: int = 0,
              seed: int = 0, base_tol: float | None = None, started: Calibration | None = None,
              final_polish: bool = True, progress=None, early_stop=None, early_steps: int = 0) -> Calibration:
    """The calibration path every client uses: start, base set at the start, bias stages (and multi-start), then
    the all-parameter polish (`polish`, with base and final_polish).
    started: an earlier calibration of the same problem and settings, whose start (and its Jacobian) is reused; the
    returned compile_s and run_s then include its own.
    progress: called with a short text as each stage begins (a progress display: `jaxcal calibrate`).
    early_stop(problem, x, J, estimated, r=weighted residuals at x) -> bool, with early_steps > 0, for an unbiased
    single-stage fit by the core's LM without multi-start (the optimistix solvers take no step limit): the fit runs
    early_steps iterations first; converged by then, it goes on as without; else early_stop is asked at that point, and
    True returns the calibration there (`stopped_early`, unconverged, no polish), False solves again from the stage's
    start with the full step limit (the result is the one without early_stop, at the cost of early_steps iterations)."""
    say = progress or (lambda text: None)
    t0 = time.perf_counter()
    reused = started is not None and started.problem is problem
    if reused:
        x_frames, registered, r0, J0, frames_ok, compile_s, frames_fitted, T0 = (
            started.x_frames, started.registered, started.r0, started.J0, started.frames_converged, 0.0, started.frames_fitted,
            started.factor0)
    else:
        say("start: device frame registered, then fitted with the nominal robot")
        P = len(problem.names)  # the solver's program, compiled first: `Problem.jacobian` runs it too
        arrays = problem.solver_arrays(problem.a_ref, np.ones(P), problem.w, 0.0, np.ones(P))
        compiled_already, compile_s = evaluator(problem, arrays, settings, compile=False)
        if compiled_already is None:  # the prior's residual programs compile beside it; compiled, a thread only costs
            prior = residuals_in_background(problem)  # (Stanford arm, 200 poses, new data each call: 2.5 ms of 29)
            _, compile_s = evaluator(problem, arrays, settings)
            prior.join()
        x_frames, frames_sol, registered = start(problem, settings, full=True, factor=base)
        # the base set's Jacobian with its factor (`choose_estimated`), where the start's solve did not return them
        r0, J0, T0 = (problem.read(x_frames, factor=base) if frames_sol is None or frames_sol.J is None
                      else (*frames_sol.read, frames_sol.factor))
        frames_ok = True if frames_sol is None else frames_sol.converged
        compile_s += 0.0 if frames_sol is None else frames_sol.compile_s
        frames_fitted = np.zeros(0, int) if frames_sol is None else frames_sol.estimated
    est, undetermined, no_effect, regrouped = choose_estimated(problem, J0, base, base_tol, T0)
    x, iterations, converged, histories = x_frames, 0, True, []
    read, T = (None if r0 is None else (r0, J0)), T0  # (r, J) at x: the next stage's start; the factor of [J r] there
    stop = offset_stop(problem, len(est))
    schedule, polishing = bias_schedule(bias), base and final_polish
    for k, mu in enumerate(schedule):
        factor = polishing and k == len(schedule) - 1  # the polish's F test starts from the last stage's factor
        say(f"fit of {len(est)} parameters" + (f", bias mu = {mu:g}" if mu else "")
            + (f", {multistart + 1} starts" if multistart else ""))
        if multistart:
            args = problem.args(est, mu, x_frames, ref_residuals=r0)
            rng = np.random.default_rng(seed)
            spread = np.zeros((multistart, len(x)))
            spread[:, est] = problem.x_scale[est] * rng.uniform(-1, 1, (multistart, len(est)))
            x0s = jnp.asarray(np.concatenate([x[None], x[None] + spread]))
            xs, oks, steps, costs, dt = solve_batch(problem, x0s, args, settings, ("x0",))
            best = int(np.argmin(np.where(oks, costs, np.inf))) if oks.any() else int(np.argmin(costs))
            sol = Solution(np.where(np.asarray(args["mask"]) > 0, xs[best], x_frames), bool(oks[best]), int(steps[best]),
                           float(costs[best]), dt)
        elif (early_stop is not None and early_steps > 0 and bias_schedule(bias) == [0.0]
              and isinstance(make_solver(settings.solver, settings.rtol, settings.atol), LevenbergMarquardt)):
            sol = solve(problem, x, est, settings, mu, ref=x_frames, limit=early_steps, start=read, ref_residuals=r0,
                        stop=stop, factor=factor)
            if not sol.converged and sol.J is not None and early_stop(problem, sol.x, sol.J, est, r=sol.r):
                return Calibration(problem, sol.x, x_frames, est, undetermined, no_effect, regrouped, sol.J, False,
                                   frames_ok, sol.steps, registered, compile_s + sol.compile_s,
                                   time.perf_counter() - t0 - compile_s - sol.compile_s, sol.history, J0, frames_fitted,
                                   {"tried": False}, stopped_early=True, r0=r0, r=sol.r, factor0=T0)
            if not sol.converged:
                compile_s += sol.compile_s
                sol = solve(problem, x, est, settings, mu, ref=x_frames, start=read, ref_residuals=r0, stop=stop, factor=factor)
        else:
            sol = solve(problem, x, est, settings, mu, ref=x_frames, start=read, ref_residuals=r0, stop=stop, factor=factor)
        histories.append(sol.history)
        x, compile_s, read, T = sol.x, compile_s + sol.compile_s, sol.read, sol.factor
        iterations += sol.steps
        converged = converged and sol.converged
    r, J = problem.residual_and_jacobian(x) if read is None else read  # the last stage's solver returned them at x
    polish_record, R = {"tried": False}, None
    if polishing:
        say("final all-parameter stage (tried when it would lower the cost beyond noise)")
        T = triangular(J, r) if T is None else T  # the polish's F test and, kept, J's own factor
        R = T[:min(J.shape), :J.shape[1]]
        polished, polish_record = polish(problem, x, J, est, undetermined, settings, r, T)
        if polished is not None:  # a converged optimum from where the stages stopped, converged or not
            R = None if polished.factor is None else polished.factor[:min(J.shape), :J.shape[1]]
            x, compile_s, converged = polished.x, compile_s + polished.compile_s, True
            iterations += polished.steps
            histories.append(polished.history)
            r, J = problem.residual_and_jacobian(x) if polished.J is None else polished.read
    run_s = time.perf_counter() - t0 - compile_s
    if reused:  # the calibration's times include those of the one whose start it took
        compile_s, run_s = compile_s + started.compile_s, run_s + started.run_s
    history = np.concatenate(histories) if histories and all(h.size for h in histories) else np.zeros(0)
    return Calibration(problem, x, x_frames, est, undetermined, no_effect, regrouped, J, converged, frames_ok, iterations,
                       registered, compile_s, run_s, history, J0, frames_fitted, polish_record, r0=r0, r=r, factor=R,
                       factor0=T0)


def closes(robot: Robot, a, q) -> np.ndarray:
    """Per-sample flags (numpy): the loops of the closed mechanism close at the robot parameters a (`jaxcal.closure.closed`),
    in the program of the sample count's bucket (`buckets`)."""
    from jaxcal.closure import closed

    q = np.asarray(q, float)
    return np.asarray(closed(robot, jnp.asarray(a), buckets.repeat_row(q, buckets.sample_bucket(len(q)), 0)))[:len(q)]


def drop_unclosed(robot: Robot, a0, q) -> np.ndarray:
    """Mask of the samples whose loops close at a0 (all True for open chains); warns naming the others."""
    if robot.closure is None:
        return np.ones(len(q), bool)
    ok = closes(robot, a0, q)
    if not ok.any():
        raise ValueError(f"no sample of {robot.name!r} closes at the starting parameters (samples 0..{len(ok) - 1})")
    if not ok.all():
        bad = np.flatnonzero(~ok).tolist()
        warnings.warn(f"{robot.name}: {len(bad)} sample(s) do not close at the starting parameters and are left out: "
                      f"{bad[:20]}{' ...' if len(bad) > 20 else ''}", stacklevel=3)
    return ok


__all__ = ["Calibration", "Problem", "RobotDevice", "SOLVERS", "START_STOP", "Settings", "Solution", "calibrate",
           "choose_estimated", "closes",
           "compiled_model_solver", "compiled_solver", "drop_unclosed", "evaluator", "f_ratio", "frames_estimated",
           "jacobian", "linear_f_ratio", "misfit",
           "make_problem", "make_solver", "model_residuals", "model_stacked", "no_covariates", "offset_stop", "polish",
           "predicted", "readings",
           "registered_frame", "residuals", "reweighted", "rigid_registration", "similarity_registration", "solve", "solve_batch",
           "solver_settings", "stacked", "step_limit", "stacked_basis", "stacked_scaled", "start", "triangular", "weighted_residuals",
           "x_scale"]
