"""The health of a calibration: what may make its numbers wrong, checked on every result.

`assess(cal)` looks at one `core.Calibration` and returns a `Health` record:

- convergence: every solver stage (frames-only start, each bias stage) met its tolerance;
- residual against the stated instrument noise: the weighted residual standard deviation
  s = sqrt(r^T r / (m - p)) (m used residual rows, p estimated parameters) is ~1 when the sigmas
  given to `identify` are the instrument's noise and the model explains the data; s > RESIDUAL_LIMIT
  says the model does not (wrong joint columns, wrong units, wrong robot, or an unmodelled effect);
- outliers: samples whose weighted error norm e_i lies more than OUTLIER_Z robust standard deviations
  above the median (scale 1.4826 MAD, which a few gross errors do not inflate);
- joint readings outside the robot's limits;
- identifiability: the number of estimated parameters, the condition number of the Jacobian with
  columns at their typical size, and the free parameters the data cannot separate;
- loop closure: samples of a closed mechanism that do not close at the start or at the solution;
- implausible corrections: robot parameters moved beyond PLAUSIBLE_CHANGE from nominal (0.1 m,
  0.5 rad, 10 % of a gain), e.g. a joint axis turned by pi to absorb a sign-flipped joint column.

A result is `ok` when none of these raised a warning; the report shows the warnings first and the
command line exits 1 for them unless told `--accept-warnings`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxcal.fit import core

RESIDUAL_LIMIT = 3.0  # weighted residual standard deviation above this multiple of the stated noise: a warning
OUTLIER_Z = 6.0  # robust z-score of a sample's error norm above which it is flagged
CONDITION_LIMIT = 1e8  # scaled condition number above which the estimate is called ill-conditioned
LIMIT_TOL = 1e-6  # joint readings this far (rad or m) beyond a limit are outside it
# Largest change from nominal that is still a calibration correction, per unit kind; beyond it the nominal
# model or the data is wrong (a joint direction flipped shows as an angle moved by pi).
PLAUSIBLE_CHANGE = {"length": 0.1, "angle": 0.5, "gain": 0.1, "scale": 0.1}


@dataclasses.dataclass(frozen=True)
class Health:
    """What may make a calibration wrong. `warnings` holds one sentence per problem; `ok` when there is none."""

    converged: bool
    residual_ratio: float  # weighted residual standard deviation (1 = at the stated instrument noise)
    outliers: tuple[int, ...]  # sample indices (in the data given) flagged by the robust test
    outside_limits: tuple[tuple[int, str], ...]  # (sample, joint name) with readings beyond the joint limits
    rank: int  # parameters estimated (the base set)
    condition: float | None  # condition number of the scaled Jacobian of the estimated parameters
    undetermined: tuple[str, ...]
    unclosed: tuple[int, ...]  # closed mechanisms: samples that do not close at the start or at the solution
    suspects: tuple[str, ...] = ()  # likely mistakes in the joint columns (swap / sign), when the residual is bad
    implausible: tuple[str, ...] = ()  # robot parameters moved beyond PLAUSIBLE_CHANGE from nominal
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return not self.warnings

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["ok"] = self.ok
        d["outside_limits"] = [list(x) for x in self.outside_limits]
        return d

    def lines(self) -> list[str]:
        """The report's first lines: the verdict and every warning."""
        if self.ok:
            return [f"health: ok (residual {self.residual_ratio:.3g} x the stated noise, {self.rank} parameters estimated)"]
        return [f"health: {len(self.warnings)} warning(s)"] + [f"  warning: {w}" for w in self.warnings]


def robust_outliers(e, z: float = OUTLIER_Z) -> np.ndarray:
    """Indices of the values of e more than z robust standard deviations (1.4826 MAD) above the median."""
    e = np.asarray(e, float)
    if e.size < 8:
        return np.zeros(0, int)
    med = np.median(e)
    scale = 1.4826 * np.median(np.abs(e - med))
    if scale <= 0:
        return np.zeros(0, int)
    return np.flatnonzero(e > med + z * scale)


def outside_joint_limits(robot, q) -> tuple[tuple[int, str], ...]:
    """(sample, joint name) of every joint reading beyond the robot's limits."""
    q = np.asarray(q, float)
    lo, hi = np.asarray(robot.q_min, float), np.asarray(robot.q_max, float)
    bad = (q < lo - LIMIT_TOL) | (q > hi + LIMIT_TOL)
    return tuple((int(i), robot.joint_names[j]) for i, j in zip(*np.nonzero(bad)))


def residual_ratio(cal: core.Calibration) -> float:
    """sqrt(r^T r / (m - p)) of the weighted residual at the solution, over the used rows."""
    r = cal.residuals[cal.problem.used]
    dof = max(r.size - len(cal.estimated), 1)
    return float(np.sqrt(np.sum(r**2) / dof))


def scaled_condition(cal: core.Calibration) -> float | None:
    """Condition number of the Jacobian of the estimated columns, each at its typical size (`core.x_scale`)."""
    if not len(cal.estimated):
        return None
    Js = cal.R[:, cal.estimated] * core.x_scale(cal.problem.units)[cal.estimated]  # J's singular values
    s = np.linalg.svd(Js, compute_uv=False)
    return float(s[0] / max(s[-1], 1e-300))


def suspect_joint_columns(problem: core.Problem, x, settings: core.Settings, improvement: float = 10.0) -> tuple[str, ...]:
    """Which joint columns are likely swapped or sign-flipped: each swap of two columns and each sign flip is
    tried with only the device frame and marker refitted from the registered start; a change that lowers the
    frames-only cost `improvement`-fold below the data as given is named (best first)."""
    robot = problem.robot
    names = robot.joint_names

    def frames_cost(q):
        trial = dataclasses.replace(problem, q=q)
        x0, sol, _ = core.start(trial, settings)
        return trial.cost(x0)

    base = frames_cost(problem.q)
    found = []
    n = problem.q.shape[1]
    for i in range(n):
        q = problem.q.copy()
        q[:, i] = -q[:, i]
        found.append((frames_cost(q), f"the sign of {names[i]} looks flipped"))
        for j in range(i + 1, n):
            q = problem.q.copy()
            q[:, [i, j]] = q[:, [j, i]]
            found.append((frames_cost(q), f"columns {names[i]} and {names[j]} look swapped"))
    return tuple(f"{why} (frames-only cost {c / base:.2g} x that of the data as given)"
                 for c, why in sorted(found) if c * improvement < base)


def implausible_changes(robot, a) -> tuple[str, ...]:
    """Robot parameters of `a` farther from nominal than PLAUSIBLE_CHANGE of their unit kind ("name (change)")."""
    change = np.asarray(a, float)[:robot.n_params] - robot.nominal_np
    limit = np.array([PLAUSIBLE_CHANGE.get(u, np.inf) for u in robot.units])
    return tuple(f"{robot.names[i]} ({change[i]:+.3g})" for i in np.flatnonzero(np.abs(change) > limit))


def assess(cal: core.Calibration, *, unclosed_start=(), sample_index=None, check_columns: bool = True,
           settings: core.Settings | None = None) -> Health:
    """The health record of one calibration. unclosed_start: samples left out because they did not close at the
    start; sample_index: the original index of each row of the problem's data (default 0..N-1)."""
    p = cal.problem
    robot = p.robot
    idx = np.arange(len(p.q)) if sample_index is None else np.asarray(sample_index)
    warnings = []
    converged = cal.converged and cal.frames_converged
    if not cal.frames_converged:
        warnings.append("the device-frame start (frames-only fit) did not converge")
    if not cal.converged:
        warnings.append(f"the solver stopped after {cal.iterations} steps without meeting its tolerance "
                        "(raise max_steps / --max-steps, or check the data)")
    ratio = residual_ratio(cal)
    suspects = ()
    if ratio > RESIDUAL_LIMIT:
        warnings.append(f"the residual is {ratio:.3g} x the stated instrument noise: the model does not explain the data "
                        "(swapped or sign-flipped joint columns, wrong units or robot file, or an unmodelled effect: "
                        "`jaxcal diagnose`)")
        if check_columns and robot.closure is None and settings is not None:
            suspects = suspect_joint_columns(p, cal.x, settings)
            warnings += [f"joint columns: {s}" for s in suspects[:3]]
    used = p.used
    norms = np.linalg.norm(cal.residuals, axis=1)
    flagged = idx[np.flatnonzero(used)[robust_outliers(norms[used])]]
    if flagged.size:
        warnings.append(f"{flagged.size} outlier sample(s) (error more than {OUTLIER_Z:g} robust standard deviations above "
                        f"the median): {flagged[:10].tolist()}{' ...' if flagged.size > 10 else ''}")
    limits = tuple((int(idx[i]), j) for i, j in outside_joint_limits(robot, p.q))
    if limits:
        warnings.append(f"{len(limits)} joint reading(s) outside the robot's limits, e.g. sample {limits[0][0]} joint "
                        f"{limits[0][1]} (degrees read as radians, a wrong robot file, or wrong columns?)")
    cond = scaled_condition(cal)
    if cond is not None and cond > CONDITION_LIMIT:
        warnings.append(f"ill-conditioned estimate (scaled condition number {cond:.3g}): some estimated parameters are "
                        "barely separable; their values are unreliable")
    unclosed = tuple(int(i) for i in unclosed_start)
    if robot.closure is not None:
        ok = core.closes(robot, cal.x[:robot.n_params], p.q)
        unclosed += tuple(int(idx[i]) for i in np.flatnonzero(~ok & used))
    if unclosed:
        warnings.append(f"{len(unclosed)} sample(s) do not close (left out or not closable at the solution): "
                        f"{sorted(set(unclosed))[:10]}")
    implausible = implausible_changes(robot, cal.x)
    if implausible:
        warnings.append(f"{len(implausible)} parameter(s) moved beyond a calibration correction (0.1 m, 0.5 rad, 10 % gain): "
                        f"{', '.join(implausible[:5])} (a flipped joint direction, wrong zero or wrong robot file?)")
    names = p.names
    return Health(converged, ratio, tuple(int(i) for i in flagged), limits, len(cal.estimated), cond,
                  tuple(names[i] for i in cal.undetermined), tuple(sorted(set(unclosed))), suspects, implausible,
                  tuple(warnings))


__all__ = ["Health", "assess", "implausible_changes", "outside_joint_limits", "residual_ratio", "robust_outliers", "scaled_condition",
           "suspect_joint_columns"]
