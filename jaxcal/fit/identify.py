"""`identify`: calibration of a robot and its measurement device from a dataset, and its `FitResult`.

`identify` builds a `jaxcal.fit.core.Problem` from the dataset and its options and solves it through
`core.calibrate`, the path every client shares. The unknowns are the free robot parameters and the
free device parameters (device frame and marker offset: unknown by default). For a rank-deficient
problem only the base set (seed 001 Appendix III, `jaxcal.fit.base`) is estimated and the other
columns stay at their prior values; they are reported as undetermined. Options from seed 004 §3.3: bounds as a penalty, the bias
term mu (a - a0) with decreasing mu (eq 3.12), and multi-start.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcal import compiled
from jaxcal.fit import bias as bias_rules
from jaxcal.fit import buckets, core, lm
from jaxcal.fit.bias import (
    ILL_CONDITIONED_BIAS,
    NOISE_DOMINATED,
    PRIOR_PATH,
    choose_bias,
    few_readings,
    weakest_standard_error,
)
from jaxcal.fit.data import Dataset
from jaxcal.fit.health import Health, assess
from jaxcal.fit.sessions import (
    INCONSISTENT,
    SESSION,
    readings_for,
    session_dataset,
    session_device_params,
    session_labels,
    session_summary,
    summary_lines,
)
from jaxcal.kin.model import Robot
from jaxcal.measure.devices import Device
from jaxcal.measure.sessions import Sessions
from jaxcal.names import check_names

SOLVERS = tuple(core.SOLVERS)
residuals = core.residuals


REVERSE_MODE_SOLVERS = ("dogleg", "bfgs")  # optimistix solvers that transpose the Jacobian


def residual_weights(device: Device, sigma_position=1e-3, sigma_orientation=1e-3):
    """Per-component weights 1/sigma for one sample's residual vector (`Device.weights`)."""
    return device.weights(sigma_position, sigma_orientation)


@functools.lru_cache(maxsize=16)
def _history_fns(robot, device, settings: core.Settings):
    """Jitted (init, step, done, cost) of an optimistix solver, built once per robot/device/settings: the data
    and weights are arguments, so every later call of `identify(history=True)` reuses the compile."""
    slv = core.make_solver(settings.solver, settings.rtol, settings.atol)
    cost = jax.jit(lambda x, args: jnp.sum(core.stacked(robot, device, x, args) ** 2))
    fn = lambda x, a: (core.stacked(robot, device, x, a), None)  # noqa: E731

    def init(x, args):
        f_struct = jax.eval_shape(lambda z: fn(z, args)[0], x)
        return slv.init(fn, x, args, {}, f_struct, None, frozenset())

    step = eqx.filter_jit(lambda x, s, args: slv.step(fn, x, args, {}, s, frozenset())[:2])
    done = eqx.filter_jit(lambda x, s, args: slv.terminate(fn, x, args, {}, s, frozenset())[0])
    return init, step, done, cost


compiled.register(_history_fns.cache_clear)


def _history(problem: core.Problem, x0, args, settings: core.Settings):
    """Cost after each step of an optimistix solver (for convergence plots), by stepping it by hand (the core's
    LM records its history in the solve itself: `core.Calibration.history`)."""
    init, step, done, cost = _history_fns(problem.robot, problem.device, settings)
    x0 = jnp.asarray(x0)
    state = init(x0, args)
    x, hist = x0, [float(cost(x0, args))]
    for _ in range(settings.max_steps):
        x, state = step(x, state, args)
        hist.append(float(cost(x, args)))
        if bool(done(x, state, args)):
            break
    return np.array(hist)


@dataclasses.dataclass
class FitResult:
    """Outcome of `identify`.

    rms_before / rms_after: RMS of the per-sample 3-D position error in mm (orientation-only
    devices: RMS angle error in mrad); `rms_before` is the fair "before": nominal robot with
    the unknown device frame and marker fitted. Orientation RMS (mrad) for pose devices is in
    `orientation_rms_before/after`.
    """

    robot: Robot
    device: Device
    a: jnp.ndarray
    device_params: jnp.ndarray
    names: tuple[str, ...]  # robot names + device names, the order of a_full
    rms_before: float
    rms_after: float
    orientation_rms_before: float | None
    orientation_rms_after: float | None
    rms_nominal: float
    iterations: int
    converged: bool
    jacobian: np.ndarray  # weighted residual Jacobian at the solution, all columns of a_full
    estimated: tuple[str, ...]  # parameters estimated (the base set among the free ones)
    undetermined: tuple[str, ...]  # free parameters the main fit could not separate (kept at prior, or see held_at_start)
    no_effect: tuple[str, ...]
    regrouped: tuple[str, ...]
    weak_directions: list  # near-zero singular directions at the solution: (sigma, {name: weight})
    timings: dict
    history: np.ndarray | None = None
    sigma: float | None = None  # residual standard deviation (weighted units) at the solution
    covariance: np.ndarray | None = None  # linearised covariance of the estimated parameters (seed 004 eq 3.31-3.32)
    info: dict = dataclasses.field(default_factory=dict)
    health: Health | None = None  # convergence, residual vs stated noise, outliers, limits, rank, closure (`fit.health`)
    held_at_start: tuple[str, ...] = ()  # undetermined device parameters fitted by the start (frames only), then held

    @property
    def std_errors(self) -> dict:
        """Standard error of each estimated parameter (sqrt of the covariance diagonal), and of each undetermined
        one the final all-parameter stage moved (`_polished_covariance`)."""
        if self.covariance is None:
            return {}
        se = dict(zip(self.estimated, np.sqrt(np.maximum(np.diag(self.covariance), 0.0))))
        return se | self.info.get("polished_std_errors", {})  # the undetermined ones the final stage moved

    def poorly_determined(self, relative: float = 0.1) -> list[str]:
        """Estimated parameters whose standard error exceeds `relative` x their typical size
        (0.01 m/rad for geometry, 1 for gains) - plus every undetermined one."""
        units = dict(zip(self.names, tuple(self.robot.units) + tuple(self.device.units)))
        out = [n for n, se in self.std_errors.items()
               if n not in self.undetermined and se > relative * (1.0 if units[n] in ("gain", "scale") else 0.01)]
        return out + list(self.undetermined)

    def status(self, name: str) -> str:
        """"estimated", "fitted at start, held" (a device parameter the start fitted that the main fit could not
        separate from robot parameters), "undetermined" (kept at its prior) or "fixed"; ", polished" when the
        final all-parameter stage moved the held ones (`core.polish`)."""
        if name in self.estimated:
            return "estimated"
        if name not in self.undetermined:
            return "fixed"
        status = "fitted at start, held" if name in self.held_at_start else "undetermined"
        return status + ", polished" if self.polished else status

    @property
    def polished(self) -> bool:
        """The final all-parameter stage was kept (`core.polish`): undetermined parameters moved a little."""
        return bool(self.info.get("polish", {}).get("accepted"))

    @property
    def a_full(self):
        return jnp.concatenate([self.a, self.device_params])

    def predict(self, q):
        """Readings the fitted model expects at joint values q, in the device frame."""
        return core.predicted(self.robot, self.device, self.a_full, np.atleast_2d(np.asarray(q, dtype=np.float64)))

    def errors(self, data: Dataset):
        """Per-sample (position m, orientation rad) errors of this model on a dataset."""
        w = residual_weights(self.device, 1.0, 1.0)
        y = readings_for(self.device, data)
        r = core.weighted_residuals(self.robot, self.device, self.a_full, data.q, y, w)
        pe, oe = self.device.split_errors(r)
        return (None if pe is None else np.asarray(pe)), (None if oe is None else np.asarray(oe))

    def rms_on(self, data: Dataset) -> float:
        """RMS error (mm, or mrad for orientation-only) of the fitted model on another dataset."""
        pe, oe = self.errors(data)
        e = pe if pe is not None else oe
        return float(np.sqrt(np.mean(e**2)) * 1e3)

    def parameter_table(self, a_true=None) -> str:
        """Per-parameter report: nominal, identified, change (and true value and error when given)."""
        nom = np.concatenate([self.robot.nominal_np, self.device.nominal_np])
        est = np.asarray(self.a_full)
        tru = None if a_true is None else np.asarray(a_true)
        head = f"{'parameter':<14}{'nominal':>13}{'identified':>13}{'change':>12}"
        if tru is not None:
            head += f"{'true':>13}{'error':>12}"
        lines = [head + "  status"]
        for i, n in enumerate(self.names):
            line = f"{n:<14}{nom[i]:>13.6g}{est[i]:>13.6g}{est[i] - nom[i]:>12.3e}"
            if tru is not None:
                line += (f"{tru[i]:>13.6g}{est[i] - tru[i]:>12.3e}" if i < len(tru) else " " * 25)
            lines.append(line + "  " + self.status(n))
        return "\n".join(lines)

    def _samples_kind(self) -> str:
        if isinstance(self.device, Sessions):
            return f"{self.device.inner.kind} ({self.device.sessions} sessions)"
        return self.device.kind

    def report(self) -> str:
        o = ""
        if self.orientation_rms_after is not None and self.rms_after == self.rms_after:
            o = f"; orientation {self.orientation_rms_before:.4g} -> {self.orientation_rms_after:.4g} mrad"
        unit = self.device.error_unit
        lines = ([] if self.health is None else self.health.lines()) + [
            f"identified {len(self.estimated)} parameters of {self.robot.name} from "
            f"{self.info.get('n_samples', '?')} {self._samples_kind()} samples",
            f"RMS error {self.rms_before:.4g} -> {self.rms_after:.4g} {unit} (nominal, frames fitted -> calibrated){o}",
            f"iterations {self.iterations}, converged {self.converged}, "
            f"compile {self.timings.get('compile_s', 0):.2f} s, run {self.timings.get('run_s', 0) * 1e3:.1f} ms",
        ]
        prior = [n for n in self.undetermined if n not in self.held_at_start]
        moved = "then moved only by the final all-parameter stage"
        if prior:
            how = f"prior, {moved}" if self.polished else "kept at prior"
            lines.append(f"undetermined ({how}): {', '.join(prior)}")
        if self.held_at_start:
            how = moved if self.polished else "then held"
            lines.append(f"fitted with the nominal robot, {how} (not separable from robot parameters): "
                         f"{', '.join(self.held_at_start)}")
        weak = [n for n in self.poorly_determined() if n not in self.undetermined]
        if weak:
            lines.append(f"poorly determined by these data (standard error above 1 mm, 1 mrad or 0.1 of a gain; "
                         f"their values are not trustworthy): {', '.join(weak)}")
        lines += summary_lines(self.info.get("sessions", []), unit)
        p = self.info.get("polish", {})
        if p.get("accepted"):
            lines.append(f"final all-parameter stage kept: cost {p['cost_before']:.4g} -> {p['cost_after']:.4g} "
                         f"(F = {p['f_ratio']:.3g} for {p['added']} held parameters)")
        return "\n".join(lines)


def _select(names, full_names, default_mask):
    if names is None:
        return np.asarray(default_mask, bool)
    names = list(names)
    check_names(names, full_names, "free: parameter")  # UnknownNameError (a KeyError) naming the closest names
    return np.isin(np.array(full_names), names)


def _device_free(device: Device, known) -> np.ndarray:
    free = device.free_mask.copy()
    for k in known:
        free &= np.array([not (n == k or n.startswith(k + ".")) for n in device.names])
    return free


@functools.partial(jax.jit, static_argnums=0)
def _split_errors(device: Device, r):
    """`device.split_errors` of each of a stack of residual arrays (k, n, m), compiled (device static): one call for
    all of them instead of one per array (~70 us each) or of its operations one by one."""
    return jax.vmap(device.split_errors)(r)


def _rms_mm(problem: core.Problem, points) -> list[tuple[float | None, float | None]]:
    """(position RMS mm, orientation RMS mrad) of the unweighted per-sample errors over the used samples, at each
    (a_full, weighted) of points: weighted are the problem's weighted residuals (N, m) at a_full when the caller has
    them (divided by the weights, which every used sample has non-zero in each component; else evaluated)."""
    unit = residual_weights(problem.device, 1.0, 1.0)
    used = problem.used

    def unweighted(a_full, weighted):
        if weighted is not None and np.all(problem.w[used] != 0):
            return np.asarray(weighted)[used] / problem.w[used] * unit
        return core.weighted_residuals(problem.robot, problem.device, a_full, problem.q, problem.y, unit)[used]

    errors = [unweighted(a_full, weighted) for a_full, weighted in points]
    n = len(errors[0])  # the program of the sample count's bucket (`buckets`): rows of 0 past the n samples
    pe, oe = _split_errors(problem.device, np.stack([buckets.zero_rows(r, buckets.sample_bucket(n)) for r in errors]))
    rms = lambda e, k: None if e is None else float(np.sqrt(np.mean(np.asarray(e)[k, :n] ** 2)) * 1e3)  # noqa: E731
    return [(rms(pe, k), rms(oe, k)) for k in range(len(points))]


def calibrate_with_default_bias(problem: core.Problem, settings: core.Settings, *, base: bool = True, bias=None,
                                multistart: int = 0, seed: int = 0, base_tol: float | None = None,
                                progress=None) -> tuple[core.Calibration, dict]:
    """`core.calibrate` with `identify`'s bias rule (its docstring, `bias`): unbiased first; when that estimate is
    noise-dominated (decided after `fit.bias.EARLY_STEPS` iterations of the unbiased fit when it is clearly so:
    `fit.bias.clearly_noise_dominated`), again from the same start with ILL_CONDITIONED_BIAS (an open chain), with
    the end of BIAS_PATH chosen by k-fold held-out error (a closed mechanism), or, for an open chain with few readings,
    every free parameter under PRIOR_PATH stopped by k-fold held-out error. Every caller that stands for
    `identify` on some samples (the gap diagnosis' fold baselines) uses this, so its result is identify's.
    Returns (calibration, record of the rule: bias_schedule, bias_every_free, weakest_standard_error, ...)."""
    rule = bias is None or (isinstance(bias, str) and bias == "heldout")
    cal = core.calibrate(problem, settings, base=base, bias=None if isinstance(bias, str) else bias, multistart=multistart,
                         seed=seed, base_tol=base_tol, progress=progress,
                         early_stop=bias_rules.clearly_noise_dominated if rule else None, early_steps=bias_rules.EARLY_STEPS)
    bias_info = {"unbiased_stopped_after": cal.iterations} if cal.stopped_early else {}
    if rule:
        weakest = weakest_standard_error(cal)
        if weakest > NOISE_DOMINATED:  # noise-dominated estimate: stop the bias schedule above 0
            every_free = bias is None and base and problem.robot.closure is None and few_readings(cal)
            if every_free:  # every free parameter under the bias, where it stops chosen by k-fold (`fit.bias`)
                cal = dataclasses.replace(cal, estimated=np.flatnonzero(problem.free))
                schedule, scores, record = choose_bias(problem, cal, settings, path=PRIOR_PATH)
                bias_info.update(bias_heldout=scores.tolist(), **record)  # NaN: a stage not run
            elif bias is None and problem.robot.closure is None:
                schedule = list(ILL_CONDITIONED_BIAS)
            else:  # bias="heldout", and a closed mechanism by default: the stop chosen by k-fold held-out error
                schedule, scores, record = choose_bias(problem, cal, settings)
                bias_info.update(bias_heldout=scores.tolist(), **record)  # NaN: a stage not run
            bias_info.update(bias_schedule=schedule, bias_every_free=every_free)
            cal = core.calibrate(problem, settings, base=base and not every_free, bias=schedule, multistart=multistart,
                                 seed=seed, base_tol=base_tol, started=cal, progress=progress)
        bias_info["weakest_standard_error"] = weakest
    return cal, bias_info


def identify(
    robot: Robot,
    data: Dataset,
    *,
    free=None,
    known=(),
    a0=None,
    device_params=None,
    solver="lm",
    base: bool = True,
    bias=None,
    bounds=None,
    multistart: int = 0,
    seed: int = 0,
    sigma_position: float = 1e-3,
    sigma_orientation: float = 1e-3,
    max_steps: int = 200,
    rtol: float = core.Settings.rtol,
    atol: float = core.Settings.atol,
    history: bool = False,
    sample_weights=None,
    base_tol: float | None = None,
    outliers: str = "flag",
    progress=None,
    session_params=("dev",),
    _unclosed_excluded: tuple = (),
) -> FitResult:
    """Identify robot and device parameters from a dataset, through the calibration core (`jaxcal.fit.core`).

    free: robot parameter names to estimate (default: the robot's free mask).
    known: device parameter prefixes or names treated as known ("dev", "tool", "dev.x", ...).
    a0, device_params: starting/prior values (default nominal; the device frame is registered onto the
    readings when that lowers the cost, then every free device parameter is fitted: `core.start`).
    solver: a name of `core.SOLVERS` ("lm" default, "lm_normal", "gn", "gn_normal", "dogleg", "bfgs") or an
    optimistix least-squares solver object.
    base: estimate only the base set of the free columns (seed 001 App. III); others stay at a0.
    bias: mu, or a decreasing sequence of mu, for the term mu ||(x - x0)/scale||^2 (seed 004 eq 3.12). Default
    (None): no bias, unless the unbiased estimate is noise-dominated (some estimated parameter's linearised
    standard error above `fit.bias.NOISE_DOMINATED` x its typical size: 1 mm / 1 mrad); then, for an open chain,
    the schedule `fit.bias.ILL_CONDITIONED_BIAS` (ending at mu = 1e-5, not 0), and for a closed mechanism the end
    of `fit.bias.BIAS_PATH` chosen by k-fold held-out error as with "heldout" (docs/delta.md: Delta simulation 3
    over six noise draws, worst error at new settings 0.39-1.79 mm; the fixed 1e-5 end gave 0.95-8.05 mm),
    except for an open chain with fewer than `fit.bias.FEW_READINGS` readings per estimated
    parameter (`fit.bias.few_readings`): there every free parameter (not the base set) is estimated under
    the schedule `fit.bias.PRIOR_PATH`, stopped where the k-fold held-out reading error is least
    (`fit.bias.choose_bias`; docs/defaults.md: a TALOS arm from 20 positions, held-out 1.26 -> 0.21 mm).
    "heldout": when noise-dominated, the end of `fit.bias.BIAS_PATH` chosen by k-fold on the base set. The
    schedule used is in `info["bias_schedule"]`; with a bias still on at the end, the covariance is the
    regularised one (`_covariance`).
    bounds: {name: (low, high)} enforced by a penalty (seed 004 §3.3).
    multistart: number of extra random starts (vmapped), spread 1 cm / 0.01 rad around a0.
    sigma_position, sigma_orientation: residual weights 1/sigma (m, rad).
    sample_weights: optional (N,) extra weight per sample (0 leaves a sample out exactly).
    base_tol: QR pivot threshold of the base set relative to the largest (default `core.BASE_TOL` = 1e-10;
    seed 001's eq 34 uses n eps, which keeps columns dependent up to round-off).
    outliers: "flag" (default: samples failing the robust test are listed in `health` and warned about) or
    "exclude" (they are also left out, weight 0, and the fit is repeated once without them).
    progress: called with a short text as each stage begins (`core.calibrate`; the CLI's progress display).
    session_params: when the data carry a "session" covariate with two or more labels (a `session` column), the
    device parameters with these prefixes get one copy per session (`measure.sessions`: default the device
    frame, "dev"; the marker and the robot are shared); () keeps one frame for all. `info["sessions"]` and the
    report then say how consistent the sessions are (`fit.sessions.session_summary`).

    Closed mechanisms: samples that do not close at the start are left out; samples that do not close at the
    solution are left out too and the fit is repeated once without them (`info["unclosed_at_solution"]`); both
    are listed in `health.unclosed` (a warning: the report and the CLI exit code see it).

    Every result carries `health` (`jaxcal.fit.health.Health`): convergence, the residual against the stated
    sigmas, outliers, joint readings outside the limits, rank and conditioning, unclosed samples, and, when the
    residual is far above the stated noise, the joint columns that look swapped or sign-flipped.
    """
    if isinstance(bias, str) and bias != "heldout":
        raise ValueError(f"bias must be None, a number, a sequence of numbers or 'heldout', got {bias!r}")
    if outliers not in ("flag", "exclude"):
        raise ValueError(f"outliers must be 'flag' or 'exclude', got {outliers!r}")
    t_start = time.perf_counter()
    if session_params and not isinstance(data.device, Sessions) and len(session_labels(data)) > 1:
        data = session_dataset(data, session_params)  # one device frame per session
        if device_params is not None:
            device_params = session_device_params(data.device, device_params)
    device = data.device
    nr = robot.n_params
    if data.q.shape[1] != robot.n_inputs:
        raise ValueError(f"data has {data.q.shape[1]} joint columns, robot {robot.name!r} has {robot.n_inputs} inputs")
    core.make_solver(solver, rtol, atol)  # unknown names fail before any work
    if solver in REVERSE_MODE_SOLVERS and robot.closure is not None and not robot.closure.transposable:
        raise ValueError(f"solver {solver!r} needs reverse-mode derivatives (J^T), which the generic loop closure of "
                         f"{robot.name!r} (jaxcal.closure.core) does not provide; use 'lm', 'lm_optimistix' or 'gn'")
    names = tuple(robot.names) + tuple(device.names)
    a0 = robot.nominal if a0 is None else jnp.asarray(a0, dtype=jnp.float64)
    d0 = device.nominal if device_params is None else jnp.asarray(device_params, dtype=jnp.float64)
    closes = core.drop_unclosed(robot, a0, data.q)
    unclosed = tuple(int(i) for i in np.flatnonzero(~closes))
    sw = np.ones(len(data)) if sample_weights is None else np.asarray(sample_weights, float)
    if sw.shape != (len(data),) or not np.all(np.isfinite(sw)) or np.any(sw < 0):
        raise ValueError(f"sample_weights must be {len(data)} finite non-negative numbers")
    keep = np.flatnonzero(closes)
    full_data = data
    data = data.subset(keep) if unclosed else data
    free_mask = np.concatenate([_select(free, robot.names, robot.free_mask), _device_free(device, known)])
    problem = core.make_problem(robot, device, data.q, data.y, weights=residual_weights(device, sigma_position, sigma_orientation),
                                free=free_mask, a_ref=np.concatenate([np.asarray(a0), np.asarray(d0)]), bounds=bounds,
                                sample_weights=sw[keep] if sample_weights is not None else None)
    settings = core.Settings(solver, max_steps, rtol, atol)
    cal, bias_info = calibrate_with_default_bias(problem, settings, base=base, bias=bias, multistart=multistart,
                                                 seed=seed, base_tol=base_tol, progress=progress)
    health = assess(cal, unclosed_start=unclosed + tuple(_unclosed_excluded), sample_index=keep, settings=settings)
    if bias_info.get("bias_fold_solves_unconverged"):
        health = dataclasses.replace(health, warnings=health.warnings + (
            f"the bias schedule's end was chosen by k-fold held-out error from fold fits of which "
            f"{bias_info['bias_fold_solves_unconverged']} of {bias_info['bias_fold_solves']} stopped unconverged (raise max_steps / "
            "--max-steps): the choice may not be the data's",))
    if robot.closure is not None and not _unclosed_excluded:
        # re-check the closure at the solution: samples that do not close there are left out and the fit repeated
        at_solution = tuple(i for i in health.unclosed if i not in unclosed)
        if at_solution:
            sw = sw.copy()
            sw[list(at_solution)] = 0.0
            kw = dict(free=free, known=known, a0=a0, device_params=device_params, solver=solver, base=base, bias=bias,
                      bounds=bounds, multistart=multistart, seed=seed, sigma_position=sigma_position,
                      sigma_orientation=sigma_orientation, max_steps=max_steps, rtol=rtol, atol=atol, history=history,
                      base_tol=base_tol, outliers=outliers, progress=progress, session_params=session_params)
            refit = identify(robot, full_data, sample_weights=sw, _unclosed_excluded=at_solution, **kw)
            refit.info["unclosed_at_solution"] = at_solution
            return refit
    if outliers == "exclude" and health.outliers:
        sw = sw.copy()
        sw[list(health.outliers)] = 0.0
        kw = dict(free=free, known=known, a0=a0, device_params=device_params, solver=solver, base=base, bias=bias,
                  bounds=bounds, multistart=multistart, seed=seed, sigma_position=sigma_position,
                  sigma_orientation=sigma_orientation, max_steps=max_steps, rtol=rtol, atol=atol, history=history,
                  base_tol=base_tol, progress=progress, session_params=session_params)
        refit = identify(robot, full_data, sample_weights=sw, outliers="flag", _unclosed_excluded=_unclosed_excluded, **kw)
        refit.info["excluded_outliers"] = health.outliers
        return refit
    hist = None
    if history:  # the solve's own record; after a multi-start, a single solve from the start; optimistix: by hand
        if cal.history.size:
            hist = cal.history
        elif isinstance(core.make_solver(settings.solver, settings.rtol, settings.atol), lm.LevenbergMarquardt):
            hist = core.solve(problem, cal.x_frames, cal.estimated, settings).history
        else:
            hist = _history(problem, cal.x_frames, problem.args(cal.estimated, 0.0, cal.x_frames), settings)

    (nominal_p, nominal_o), (before_p, before_o), (after_p, after_o) = _rms_mm(
        problem, [(problem.a_ref, problem.prior_residuals), (cal.x_frames, cal.r0), (cal.x, cal.residuals)])
    est_idx = cal.estimated
    Je = cal.R[:, est_idx]  # J's triangular factor: J's covariance and singular directions (`core.triangular`)
    r_final = cal.residuals.reshape(-1)
    readings = int(np.sum(problem.w != 0))
    mu_end = core.bias_schedule(bias_info.get("bias_schedule", None if isinstance(bias, str) else bias))[-1]
    svd = np.linalg.svd(Je, full_matrices=False)[1:] if Je.size else None  # the covariance's and the weak directions'
    covariance, sigma_hat = _covariance(Je, mu_end, problem.x_scale[est_idx], r_final, readings, svd)
    polished_se = {}
    if cal.polish.get("accepted"):
        covariance, polished_se = _polished_covariance(cal, r_final, readings, names)
    pick = (lambda p, o: p if p is not None else o)
    to_names = lambda idx: tuple(names[i] for i in idx)  # noqa: E731
    fit = FitResult(
        robot=robot, device=device, a=jnp.asarray(cal.x[:nr]), device_params=jnp.asarray(cal.x[nr:]), names=names,
        rms_before=pick(before_p, before_o), rms_after=pick(after_p, after_o),
        orientation_rms_before=before_o if before_p is not None else None,
        orientation_rms_after=after_o if after_p is not None else None,
        rms_nominal=pick(nominal_p, nominal_o), iterations=cal.iterations, converged=cal.converged, jacobian=cal.J,
        estimated=to_names(est_idx), undetermined=to_names(cal.undetermined), no_effect=to_names(cal.no_effect),
        regrouped=to_names(cal.regrouped), weak_directions=_weak_directions(Je, to_names(est_idx), svd=svd),
        timings={"compile_s": cal.compile_s, "run_s": cal.run_s, "total_s": time.perf_counter() - t_start},
        history=hist, sigma=sigma_hat, covariance=covariance, health=health,
        held_at_start=to_names(i for i in cal.undetermined if i in set(cal.frames_fitted.tolist())),
        info={"n_samples": len(data), "unclosed_samples": unclosed, "estimated_index": est_idx,
              "solver": solver if isinstance(solver, str) else type(solver).__name__,
              "sigma_position": sigma_position, "sigma_orientation": sigma_orientation,
              "frames_converged": cal.frames_converged, "registered_start": cal.registered, "polish": cal.polish,
              "polished_std_errors": polished_se,
              **bias_info},
    )
    if isinstance(device, Sessions):
        _add_session_summary(fit, data)
    return fit


def _add_session_summary(fit: FitResult, data: Dataset) -> None:
    """fit.info["sessions"] (`fit.sessions.session_summary`), and a health warning naming the sessions whose RMS
    error is far above the others' (the instrument moved during the session, or a different set-up)."""
    rows = session_summary(fit, data)
    fit.info["sessions"] = rows
    bad = [r["session"] for r in rows if r["inconsistent"]]
    if bad and fit.health is not None:
        msg = (f"session(s) {', '.join(bad)}: RMS error above {INCONSISTENT:g}x the other sessions' median (instrument "
               "moved during the session, or another set-up)")
        fit.health = dataclasses.replace(fit.health, warnings=fit.health.warnings + (msg,))


PINV_RCOND = 1e-15  # numpy.linalg.pinv's default relative cut-off, on the singular values of J^T J (those of J squared)


def _covariance(J, mu: float, scale, r, readings: int, svd=None) -> tuple[np.ndarray | None, float]:
    """(covariance, sigma): the linearised covariance of the estimate and the weighted residual's standard
    deviation (seed 004 eq 3.31-3.32). Without bias: sigma^2 (J^T J)^+, sigma^2 = r^T r / (readings - p). With the
    bias mu ||(x - x_ref) / s||^2 still on at the end (seed 004 eq 3.12 read as a prior): A = J^T J + mu
    diag(1 / s^2), covariance sigma^2 A^-1, and the degrees of freedom readings - tr(A^-1 J^T J) (the effective
    number of parameters, below p where the bias holds directions the data leave open). Directions the data do
    not determine then keep the prior's spread s / sqrt(mu) instead of an arbitrary pseudo-inverse value.
    svd: (s, Vt) of J (`numpy.linalg.svd`, full_matrices False) when the caller has it: (J^T J)^+ = V diag(1 / s^2) V^T
    over the s^2 above PINV_RCOND s_1^2, without the squared condition of factoring J^T J itself."""
    if J.shape[1] == 0:
        return None, float(np.sqrt(r @ r / max(readings, 1)))
    if mu > 0:
        JtJ = J.T @ J
        A_inv = np.linalg.inv(JtJ + mu * np.diag(1.0 / np.asarray(scale) ** 2))
        sigma = float(np.sqrt(r @ r / max(readings - np.trace(A_inv @ JtJ), 1.0)))
        return sigma**2 * A_inv, sigma
    sigma = float(np.sqrt(r @ r / max(readings - J.shape[1], 1)))
    s, Vt = np.linalg.svd(J, full_matrices=False)[1:] if svd is None else svd
    inverse = np.divide(1.0, s**2, out=np.zeros_like(s), where=s**2 > PINV_RCOND * s[0] ** 2)
    return sigma**2 * (Vt.T * inverse) @ Vt, sigma


def _polished_covariance(cal: core.Calibration, r, readings: int, names) -> tuple[np.ndarray, dict]:
    """Covariance after the final all-parameter stage (`core.polish`): the stage solved every parameter with an
    effect under the bias mu ||(x - x_ref) / s||^2, mu = POLISH_BIAS, so its information is
    J^T J + mu diag(1 / s^2) over those columns (seed 004 eq 3.12 read as a prior) and its covariance
    sigma^2 (J^T J + mu diag(1 / s^2))^-1. Returns (the block of the estimated parameters, {name: standard
    error} of the parameters the stage added). Directions the data cannot determine keep the prior's spread
    (s / sqrt(mu) = 0.1 m or rad, `_covariance`) instead of the tiny error the base-set block gives when the
    held parameters are not at their true values."""
    added = np.asarray(cal.polish["added_index"], int)  # the held parameters the stage solved (`core.polish`)
    cols = np.sort(np.concatenate([cal.estimated, added]))
    C, _ = _covariance(cal.R[:, cols], core.POLISH_BIAS, cal.problem.x_scale[cols], r, readings)
    pos = np.searchsorted(cols, cal.estimated)
    se = np.sqrt(np.maximum(np.diag(C), 0.0))
    return C[np.ix_(pos, pos)], {names[c]: float(se[k]) for k, c in enumerate(cols) if c in set(added.tolist())}


def _weak_directions(J, names, rel: float = 1e-8, svd=None):
    """Singular directions of J with sigma < rel * sigma_max, as (sigma, {name: component}); svd: (s, Vt) of J when
    the caller has it."""
    if J.size == 0:
        return []
    s, Vt = np.linalg.svd(J, full_matrices=False)[1:] if svd is None else svd
    out = []
    for k in np.flatnonzero(s < rel * s[0]):
        comp = {names[i]: float(Vt[k, i]) for i in np.argsort(-np.abs(Vt[k]))[:4] if abs(Vt[k, i]) > 0.1}
        out.append((float(s[k]), comp))
    return out


def apply_to_session(fit, data: Dataset, refit=("dev", "tool"), **identify_options):
    """A calibrated robot used on a new session: the robot held at fit.a, only the device parameters whose names
    start with `refit` fitted to this session's data (default the frame and the marker: a marker put back on the
    tool is rarely exactly where it was); the rest of the device at the calibration's values."""
    device = fit.device.inner if isinstance(fit.device, Sessions) else fit.device
    d = np.asarray(fit.device_params, float)
    if isinstance(fit.device, Sessions):
        d = d[fit.device.index[0]]  # the shared entries are the same in every session; the frame is refitted
    known = tuple(sorted({n.split(".")[0] for n in device.names} - set(refit)))
    data = Dataset(data.q, data.y, device, {k: v for k, v in data.covariates.items() if k != SESSION},
                   joint_names=data.joint_names, source=data.source)
    return identify(fit.robot, data, free=(), known=known, a0=fit.a, device_params=d, **identify_options)
