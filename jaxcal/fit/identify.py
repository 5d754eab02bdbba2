"""Identification: stacked weighted residual, autodiff Jacobian, optimistix solvers.

The unknowns are the free robot parameters and the free device parameters (device frame and
marker offset: unknown by default). For a rank-deficient problem only the base set (seed 001
Appendix III, `jaxcal.fit.base`) is estimated and the other columns stay at their prior values;
they are reported as undetermined. Options from seed 004 §3.3: bounds as a penalty, the bias
term mu (a - a0) with decreasing mu (eq 3.12), and multi-start.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from jaxcal.fit.base import base_set
from jaxcal.fit.data import Dataset
from jaxcal.forward import forward
from jaxcal.kin.model import Robot
from jaxcal.measure.devices import Device

SOLVERS = ("lm", "lm_normal", "gn", "gn_normal", "dogleg", "bfgs")


def _solver(name: str, rtol: float, atol: float):
    if name == "lm":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    if name == "lm_normal":  # normal equations by Cholesky: faster for tall Jacobians, less robust (JAX_NOTES 4)
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    if name == "gn":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    if name == "gn_normal":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.Normal(lx.Cholesky()))
    if name == "dogleg":
        return optx.Dogleg(rtol=rtol, atol=atol)
    if name == "bfgs":
        return optx.BFGS(rtol=rtol, atol=atol)
    raise ValueError(f"unknown solver {name!r}; expected one of {SOLVERS}")


def residuals(robot: Robot, device: Device, a_full, q, y, w):
    """Weighted residuals (N, m) of all samples: w * (measured - predicted)."""
    nr = robot.n_params
    tips = forward(robot, a_full[:nr], q)
    pred = jax.vmap(device.read, (0, None))(tips, a_full[nr:])
    return jax.vmap(device.residual)(pred, y) * w


def residual_weights(device: Device, sigma_position=1e-3, sigma_orientation=1e-3):
    """Per-component weights 1/sigma for one sample's residual vector (`Device.weights`)."""
    return device.weights(sigma_position, sigma_orientation)


def _stacked(robot, device, x, args):
    """Residual of the full vector x: data, the bias term on estimated entries, the bound penalty,
    and a pin (x - a_ref) on entries that are not estimated. Pinning instead of slicing keeps one
    shape for every stage (frames-only fit, base-set fit, bias stages), so one compile serves all.
    """
    m = args["mask"]
    a_full = jnp.where(m > 0, x, args["a_ref"])
    r = residuals(robot, device, a_full, args["q"], args["y"], args["w"]).reshape(-1)
    scaled = (x - args["a_ref"]) / args["x_scale"]
    bias = jnp.sqrt(args["mu"]) * m * scaled
    pin = (1.0 - m) * scaled
    over = jnp.maximum(x - args["ub"], 0.0) + jnp.maximum(args["lb"] - x, 0.0)
    return jnp.concatenate([r, bias + pin, 1e6 * m * over / args["x_scale"]])


@functools.partial(jax.jit, static_argnames=("robot", "device", "solver", "max_steps", "rtol", "atol"))
def _solve(x0, args, *, robot, device, solver, max_steps, rtol, atol):
    fn = functools.partial(_stacked, robot, device)
    sol = optx.least_squares(fn, _solver(solver, rtol, atol), x0, args, max_steps=max_steps, throw=False)
    cost = jnp.sum(fn(sol.value, args) ** 2)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"], cost


@functools.partial(jax.jit, static_argnames=("robot", "device", "solver", "max_steps", "rtol", "atol"))
def _solve_many(x0s, args, *, robot, device, solver, max_steps, rtol, atol):
    one = functools.partial(_solve.__wrapped__, robot=robot, device=device, solver=solver,
                            max_steps=max_steps, rtol=rtol, atol=atol)
    return jax.vmap(one, (0, None))(x0s, args)


_EXECUTABLES: dict = {}


def _executable(fn, cfg, x0, args):
    """Compiled `fn` for these static settings and argument shapes, and the seconds spent compiling
    (0 when it was compiled before in this process). Robots and devices hash by identity."""
    shapes = jax.tree_util.tree_map(lambda v: (jnp.shape(v), jnp.result_type(v)), (x0, args))
    key = (fn, tuple(sorted(cfg.items(), key=lambda kv: kv[0])), str(shapes))
    if key in _EXECUTABLES:
        return _EXECUTABLES[key], 0.0
    t = time.perf_counter()
    exe = fn.lower(x0, args, **cfg).compile()
    _EXECUTABLES[key] = exe
    return exe, time.perf_counter() - t


@functools.partial(jax.jit, static_argnums=(0, 1))
def _rms_residual(robot, device, a_full, q, y, w):
    return jnp.sqrt(jnp.mean(residuals(robot, device, a_full, q, y, w) ** 2))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _errors(robot, device, a_full, q, y):
    """Unweighted per-sample (position, orientation) errors."""
    r = residuals(robot, device, a_full, q, y, residual_weights(device, 1.0, 1.0))
    return device.split_errors(r)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _jacobian(robot, device, a_full, q, y, w):
    return jax.jacfwd(lambda a: residuals(robot, device, a, q, y, w).reshape(-1))(a_full)


@functools.cache
def _history_fns(robot, device, solver, rtol, atol):
    """Jitted (init, step, done, cost) of one solver, built once per robot/device/solver: the data
    and weights are arguments, so every later call of `identify(history=True)` reuses the compile."""
    slv = _solver(solver, rtol, atol)
    fn = lambda x, a: (_stacked(robot, device, x, a), None)  # noqa: E731

    def init(x, args):
        f_struct = jax.eval_shape(lambda z: fn(z, args)[0], x)
        return slv.init(fn, x, args, {}, f_struct, None, frozenset())

    step = eqx.filter_jit(lambda x, s, args: slv.step(fn, x, args, {}, s, frozenset())[:2])
    done = eqx.filter_jit(lambda x, s, args: slv.terminate(fn, x, args, {}, s, frozenset())[0])
    cost = jax.jit(lambda x, args: jnp.sum(fn(x, args)[0] ** 2))
    return init, step, done, cost


def _history(robot, device, x0, args, solver, max_steps, rtol, atol):
    """Cost after each solver step (for convergence plots), by stepping optimistix by hand."""
    init, step, done, cost = _history_fns(robot, device, solver, rtol, atol)
    state = init(x0, args)
    x, hist = x0, [float(cost(x0, args))]
    for _ in range(max_steps):
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
    undetermined: tuple[str, ...]  # free parameters the data could not separate (kept at prior)
    no_effect: tuple[str, ...]
    regrouped: tuple[str, ...]
    weak_directions: list  # near-zero singular directions at the solution: (sigma, {name: weight})
    timings: dict
    history: np.ndarray | None = None
    sigma: float | None = None  # residual standard deviation (weighted units) at the solution
    covariance: np.ndarray | None = None  # linearised covariance of the estimated parameters (seed 004 eq 3.31-3.32)
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def std_errors(self) -> dict:
        """Standard error of each estimated parameter (sqrt of the covariance diagonal)."""
        if self.covariance is None:
            return {}
        return dict(zip(self.estimated, np.sqrt(np.maximum(np.diag(self.covariance), 0.0))))

    def poorly_determined(self, relative: float = 0.1) -> list[str]:
        """Estimated parameters whose standard error exceeds `relative` x their typical size
        (0.01 m/rad for geometry, 1 for gains) - plus every undetermined one."""
        units = dict(zip(self.names, tuple(self.robot.units) + tuple(self.device.units)))
        out = [n for n, se in self.std_errors.items() if se > relative * (1.0 if units[n] in ("gain", "scale") else 0.01)]
        return out + list(self.undetermined)

    @property
    def a_full(self):
        return jnp.concatenate([self.a, self.device_params])

    def predict(self, q):
        """Readings the fitted model expects at joint values q, in the device frame."""
        tips = forward(self.robot, self.a, jnp.atleast_2d(jnp.asarray(q, dtype=jnp.float64)))
        return np.asarray(jax.vmap(self.device.read, (0, None))(tips, self.device_params))

    def errors(self, data: Dataset):
        """Per-sample (position m, orientation rad) errors of this model on a dataset."""
        w = residual_weights(self.device, 1.0, 1.0)
        r = residuals(self.robot, self.device, self.a_full, jnp.asarray(data.q), jnp.asarray(data.y), w)
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
            status = "estimated" if n in self.estimated else ("undetermined" if n in self.undetermined else "fixed")
            line = f"{n:<14}{nom[i]:>13.6g}{est[i]:>13.6g}{est[i] - nom[i]:>12.3e}"
            if tru is not None:
                line += (f"{tru[i]:>13.6g}{est[i] - tru[i]:>12.3e}" if i < len(tru) else " " * 25)
            lines.append(line + "  " + status)
        return "\n".join(lines)

    def report(self) -> str:
        o = ""
        if self.orientation_rms_after is not None and self.rms_after == self.rms_after:
            o = f"; orientation {self.orientation_rms_before:.4g} -> {self.orientation_rms_after:.4g} mrad"
        unit = self.device.error_unit
        lines = [
            f"identified {len(self.estimated)} parameters of {self.robot.name} from "
            f"{self.info.get('n_samples', '?')} {self.device.kind} samples",
            f"RMS error {self.rms_before:.4g} -> {self.rms_after:.4g} {unit} (nominal, frames fitted -> calibrated){o}",
            f"iterations {self.iterations}, converged {self.converged}, "
            f"compile {self.timings.get('compile_s', 0):.2f} s, run {self.timings.get('run_s', 0) * 1e3:.1f} ms",
        ]
        if self.undetermined:
            lines.append(f"undetermined (kept at prior): {', '.join(self.undetermined)}")
        return "\n".join(lines)


def _drop_unclosed(robot: Robot, a0, data: Dataset, sample_weights):
    """Samples of a closed mechanism whose loops do not close at the start `a0` carry no usable
    reading (seed 004 §4.3): they are dropped with a warning naming them, and their indices
    (in the given dataset) are returned so the caller can report them."""
    if robot.closure is None:
        return data, sample_weights, ()
    from jaxcal.closure import closed

    ok = np.asarray(closed(robot, a0, jnp.asarray(data.q)))
    if ok.all():
        return data, sample_weights, ()
    bad = tuple(int(i) for i in np.flatnonzero(~ok))
    if not ok.any():
        raise ValueError(f"no sample of {robot.name!r} closes at the starting parameters (samples 0..{len(ok) - 1})")
    warnings.warn(f"{robot.name}: {len(bad)} sample(s) do not close at the starting parameters and are left out: "
                  f"{list(bad)[:20]}{' ...' if len(bad) > 20 else ''}", stacklevel=3)
    keep = np.flatnonzero(ok)
    sw = None if sample_weights is None else np.asarray(sample_weights, float)[keep]
    return data.subset(keep), sw, bad


def _x_scale(units):
    """Typical size of a parameter change: 0.01 (m or rad) for geometry, 1 for gains and scales."""
    return np.array([1.0 if u in ("gain", "scale") else 0.01 for u in units])


def _select(names, full_names, default_mask):
    if names is None:
        return np.asarray(default_mask, bool)
    names = list(names)
    unknown = [n for n in names if n not in full_names]
    if unknown:
        raise KeyError(f"unknown parameter name(s) {unknown}")
    return np.isin(np.array(full_names), names)


def identify(
    robot: Robot,
    data: Dataset,
    *,
    free=None,
    known=(),
    a0=None,
    device_params=None,
    solver: str = "lm",
    base: bool = True,
    bias=None,
    bounds=None,
    multistart: int = 0,
    seed: int = 0,
    sigma_position: float = 1e-3,
    sigma_orientation: float = 1e-3,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    history: bool = False,
    sample_weights=None,
) -> FitResult:
    """Identify robot and device parameters from a dataset.

    free: robot parameter names to estimate (default: the robot's free mask).
    known: device parameter prefixes or names treated as known ("dev", "tool", "dev.x", ...).
    a0, device_params: starting/prior values (default nominal).
    solver: "lm" (default; QR linear solves), "lm_normal" (LM on the normal equations by Cholesky),
    "gn", "gn_normal", "dogleg" or "bfgs" (optimistix).
    base: estimate only the base set of the free columns (seed 001 App. III); others stay at a0.
    bias: mu, or a decreasing sequence of mu, for the term mu ||(x - x0)/scale||^2 (seed 004 eq 3.12).
    bounds: {name: (low, high)} enforced by a penalty (seed 004 §3.3).
    multistart: number of extra random starts (vmapped), spread 1 cm / 0.01 rad around a0.
    sigma_position, sigma_orientation: residual weights 1/sigma (m, rad).
    sample_weights: optional (N,) extra weight per sample (robust re-weighting, outlier removal).
    """
    t_start = time.perf_counter()
    device = data.device
    nr = robot.n_params
    if data.q.shape[1] != robot.n_inputs:
        raise ValueError(f"data has {data.q.shape[1]} joint columns, robot {robot.name!r} has {robot.n_inputs} inputs")
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {SOLVERS}")
    names = tuple(robot.names) + tuple(device.names)
    a0 = robot.nominal if a0 is None else jnp.asarray(a0, dtype=jnp.float64)
    data, sample_weights, unclosed = _drop_unclosed(robot, a0, data, sample_weights)
    d0 = device.nominal if device_params is None else jnp.asarray(device_params, dtype=jnp.float64)
    a_ref = jnp.concatenate([a0, d0])
    robot_free = _select(free, robot.names, robot.free_mask)
    dev_free = device.free_mask.copy()
    for k in known:
        dev_free &= np.array([not (n == k or n.startswith(k + ".")) for n in device.names])
    free_mask = np.concatenate([robot_free, dev_free])
    priority = np.concatenate([robot.priority, device.priority])
    units = tuple(robot.units) + tuple(device.units)

    q, y = jnp.asarray(data.q), jnp.asarray(data.y)
    w = residual_weights(device, sigma_position, sigma_orientation)
    if sample_weights is not None:
        sw = np.asarray(sample_weights, float)
        if sw.shape != (len(data),) or not np.all(np.isfinite(sw)) or np.any(sw < 0):
            raise ValueError(f"sample_weights must be {len(data)} finite non-negative numbers")
        w = jnp.asarray(sw)[:, None] * w[None, :]
    cfg = dict(robot=robot, device=device, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol)

    x_scale = jnp.asarray(_x_scale(units))
    lb, ub = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    for n, (lo, hi) in (bounds or {}).items():
        if n not in names:
            raise KeyError(f"bounds: unknown parameter {n!r}")
        lb[names.index(n)], ub[names.index(n)] = lo, hi

    def make_args(idx, mu, ref):
        """Solver arguments; the data weights are divided by the RMS weighted residual at `ref`,
        which leaves the optimum unchanged but starts LM with an O(1) residual: optimistix's
        trust region took 4 to 34 iterations on the same problem depending on that scale."""
        mask = np.zeros(len(names))
        mask[np.asarray(idx, int)] = 1.0
        w_solve = w / jnp.maximum(_rms_residual(robot, device, ref, q, y, w), 1e-12)
        return dict(a_ref=ref, mask=jnp.asarray(mask), q=q, y=y, w=w_solve, mu=jnp.float64(mu), x_scale=x_scale,
                    lb=jnp.asarray(lb), ub=jnp.asarray(ub))

    def rms_of(a_full):
        pe, oe = _errors(robot, device, a_full, q, y)
        pr = None if pe is None else float(jnp.sqrt(jnp.mean(pe**2)) * 1e3)
        orr = None if oe is None else float(jnp.sqrt(jnp.mean(oe**2)) * 1e3)
        return pr, orr

    compile_s = 0.0

    def solve(x0, args):
        nonlocal compile_s
        exe, dt = _executable(_solve, cfg, x0, args)
        compile_s += dt
        return exe(x0, args)

    # 1. The fair "before": nominal robot, unknown device frame / marker fitted.
    dev_idx = np.flatnonzero(dev_free) + nr
    a_frames = a_ref
    if dev_idx.size:
        frames_args = make_args(dev_idx, 0.0, a_ref)
        a_frames = jnp.where(frames_args["mask"] > 0, solve(a_ref, frames_args)[0], a_ref)
    nominal_p, nominal_o = rms_of(a_ref)
    before_p, before_o = rms_of(a_frames)

    # 2. Base set of the free columns at the frames-fitted point.
    J0 = np.asarray(_jacobian(robot, device, a_frames, q, y, w))
    cand = np.flatnonzero(free_mask)
    if base:
        bs = base_set(J0[:, cand], priority[cand])
        est_idx = np.sort(cand[bs.independent])
        undetermined = tuple(names[i] for i in np.sort(cand[np.concatenate([bs.regrouped, bs.no_effect])]))
        no_effect = tuple(names[i] for i in cand[bs.no_effect])
        regrouped = tuple(names[i] for i in cand[bs.regrouped])
    else:
        est_idx, undetermined, no_effect, regrouped = cand, (), (), ()

    # 3. Solve (bias stages, multi-start), always from the frames-fitted point as prior.
    mus = [0.0] if bias is None else (list(bias) if np.ndim(bias) else [float(bias) * 10.0**-k for k in range(4)] + [0.0])
    t_fit = time.perf_counter()
    compile_before = compile_s
    iterations, converged = 0, True
    x = a_frames
    for mu in mus:
        args = make_args(est_idx, mu, a_frames)
        if multistart:
            rng = np.random.default_rng(seed)
            spread = np.zeros((multistart, len(names)))
            spread[:, est_idx] = np.asarray(x_scale)[est_idx] * rng.uniform(-1, 1, (multistart, len(est_idx)))
            x0s = jnp.concatenate([x[None], x[None] + spread], axis=0)
            many, dt = _executable(_solve_many, cfg, x0s, args)
            compile_s += dt
            xs, oks, steps, costs = many(x0s, args)
            best = int(jnp.argmin(jnp.where(oks, costs, jnp.inf))) if bool(jnp.any(oks)) else int(jnp.argmin(costs))
            x, ok, n_steps = xs[best], bool(oks[best]), int(steps[best])
        else:
            x, ok, n_steps, _ = solve(x, args)
            ok, n_steps = bool(ok), int(n_steps)
        iterations += n_steps
        converged = converged and ok
    jax.block_until_ready(x)
    run_s = time.perf_counter() - t_fit - (compile_s - compile_before)
    hist = _history(robot, device, a_frames, make_args(est_idx, 0.0, a_frames), solver, max_steps, rtol, atol) if history else None

    est_mask = np.zeros(len(names), bool)
    est_mask[est_idx] = True
    a_full = jnp.where(jnp.asarray(est_mask), x, a_frames)
    after_p, after_o = rms_of(a_full)
    J = np.asarray(_jacobian(robot, device, a_full, q, y, w))
    r_final = np.asarray(residuals(robot, device, a_full, q, y, w)).reshape(-1)
    dof = max(r_final.size - len(est_idx), 1)
    weak = _weak_directions(J[:, est_idx], [names[i] for i in est_idx])
    sigma_hat = float(np.sqrt(r_final @ r_final / dof))
    covariance = sigma_hat**2 * np.linalg.pinv(J[:, est_idx].T @ J[:, est_idx]) if len(est_idx) else None
    pick = (lambda p, o: p if p is not None else o)
    return FitResult(
        robot=robot, device=device, a=a_full[:nr], device_params=a_full[nr:], names=names,
        rms_before=pick(before_p, before_o), rms_after=pick(after_p, after_o),
        orientation_rms_before=before_o if before_p is not None else None,
        orientation_rms_after=after_o if after_p is not None else None,
        rms_nominal=pick(nominal_p, nominal_o), iterations=iterations, converged=converged, jacobian=J,
        estimated=tuple(names[i] for i in est_idx), undetermined=undetermined, no_effect=no_effect,
        regrouped=regrouped, weak_directions=weak,
        timings={"compile_s": compile_s, "run_s": run_s, "total_s": time.perf_counter() - t_start},
        history=hist, sigma=sigma_hat, covariance=covariance,
        info={"n_samples": len(data), "unclosed_samples": unclosed, "estimated_index": est_idx, "solver": solver,
              "sigma_position": sigma_position, "sigma_orientation": sigma_orientation},
    )


def _weak_directions(J, names, rel: float = 1e-8):
    """Singular directions of J with sigma < rel * sigma_max, as (sigma, {name: component})."""
    if J.size == 0:
        return []
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    out = []
    for k in np.flatnonzero(s < rel * s[0]):
        comp = {names[i]: float(Vt[k, i]) for i in np.argsort(-np.abs(Vt[k]))[:4] if abs(Vt[k, i]) > 0.1}
        out.append((float(s[k]), comp))
    return out

