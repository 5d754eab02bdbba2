"""The bias term chosen by held-out error (seed 004 eq 3.12, §3.3; §4.3 Delta simulation 3).

The thesis adds mu ||a - a0||^2 to the cost and lowers mu stage by stage. Ending at mu = 0 is right for a
well-determined problem; for a noise-dominated one (theodolite angles from 3.7 m on the Delta: linearised
standard errors of several estimated parameters far above 1 mm) the last stages fit the noise along weak
directions and the calibrated model
predicts new settings worse than the nominal one. `choose_bias` picks where the schedule stops by
k-fold cross-validation over the samples: the path BIAS_PATH is solved stage by stage on all samples from the
frames-only start, each fold's estimate at every stage is one Gauss-Newton step from there with the fold's
samples left out (`fold_score`), scored on those samples (weighted residual sum of squares), and the stage
with the lowest pooled held-out score wins (`identify(bias="heldout")`, and `identify`'s default for a
noise-dominated closed mechanism). On Delta simulation 3's seed-0 draw the fixed ILL_CONDITIONED_BIAS predicted
new tool positions better (worst 0.95 mm against 1.79 mm), but over six noise draws it reached 8.05 mm where the
k-fold choice stayed below 1.8 mm (docs/delta.md); the path stops once the held-out score has risen for PATIENCE
stages in a row (the later stages are not run), and `core.calibrate` reuses its stages. Open chains keep
ILL_CONDITIONED_BIAS.
"""

from __future__ import annotations

import numpy as np

from jaxcal.fit import core

BIAS_PATH = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 0.0)  # candidate end points, in the order they are continued
# identify's default for an ill-conditioned open chain: the thesis' decreasing mu, stopped at 1e-5 instead of 0.
# Chosen by the error of the calibrated model at new settings on Delta simulation 3 (docs/delta.md: worst tool
# error 1.2 mm against 2.6 mm ending at 1e-4, 11.7 mm at 1e-6 and 62 mm at 0); one case, stated as such.
ILL_CONDITIONED_BIAS = (1e-2, 1e-3, 1e-4, 1e-5)
# the unbiased estimate is noise-dominated when some estimated parameter's linearised standard error exceeds
# this share of its typical size (`core.x_scale`: 0.01 m / 0.01 rad, i.e. 1 mm / 1 mrad); noise-free data
# (Delta simulation 2) have a standard error of ~0 and keep mu = 0
NOISE_DOMINATED = 0.1
BIAS_FOLDS = 4
# stages the held-out score may rise past its least before the path stops (`heldout_scores`)
PATIENCE = 2
# identify's default for a noise-dominated open chain with few readings: every free parameter (no base-set cut)
# under mu from strong to weak, stopped by k-fold held-out error. Few = below FEW_READINGS readings (weighted
# residual components) per estimated parameter. Chosen on docs/defaults.md's table: a TALOS arm (45 base
# parameters) from 20 positions, 60 readings: held-out 1.26 mm with the base set, 0.22 mm this way. The other
# noise-dominated cases measured keep the base set: a UR10 URDF chain from 40 positions (4.4 readings per
# parameter; its final all-parameter stage reaches the noise), the real UR10 (4.6) and TIAGo (6.0) data.
PRIOR_PATH = (10.0, 1.0, 1e-1, 1e-2, 1e-3)
FEW_READINGS = 2.0


# identify's unbiased fit, when its estimate is clearly noise-dominated, is stopped after EARLY_STEPS iterations
# (`clearly_noise_dominated`, `core.calibrate`'s early_stop): that fit only decides the rule (the bias path starts
# again from the frames-only start), and a noise-dominated one crawls along its weak directions to converge (TALOS
# left arm, 61 real positions: 122 of the call's 212 LM steps, weakest standard error 106-171 x the typical size at
# every step from 5 on; Delta, 125 positions: 57 steps, 7.2-8.6 x). Clearly: above EARLY_MARGIN x NOISE_DOMINATED with
# the residual variance that one Gauss-Newton step predicts at the optimum, so a well-determined fit that is still
# far from its optimum (its residual not yet down to the noise) goes on.
EARLY_STEPS = 20
EARLY_MARGIN = 10.0


def _weakest(Je_scaled, sigma2: float) -> float:
    """Largest sqrt(diag(sigma^2 (Je^T Je)^+)) (Je: the estimated columns in typical-size units)."""
    cov = sigma2 * np.linalg.pinv(Je_scaled.T @ Je_scaled)
    return float(np.sqrt(np.max(np.maximum(np.diag(cov), 0.0))))


def weakest_standard_error(cal: core.Calibration) -> float:
    """Largest linearised standard error of an estimated parameter, in units of its typical size: sigma^2
    (J^T J)^+ with sigma^2 = r^T r / (m - p) from the weighted residual at the solution (seed 004 eq 3.31-3.32)."""
    est = np.asarray(cal.estimated, int)
    if not est.size:
        return 0.0
    p = cal.problem
    r = np.asarray(core.weighted_residuals(p.robot, p.device, cal.x, p.q, p.y, p.w))[p.used]
    sigma2 = float(np.sum(r**2)) / max(r.size - est.size, 1)
    return _weakest(cal.J[:, est] * core.x_scale(p.units)[est], sigma2)


def clearly_noise_dominated(problem: core.Problem, x, J, estimated) -> bool:
    """Whether an unconverged fit at x (J: the weighted data Jacobian there) is noise-dominated by EARLY_MARGIN:
    `weakest_standard_error` with sigma^2 from min over delta of |r + J_e delta|^2 (the cost the linearised fit
    reaches; below the cost at x, so the test errs toward going on with the fit)."""
    est = np.asarray(estimated, int)
    if not est.size:
        return False
    r = np.asarray(problem.residuals(x))
    readings = r[problem.used].size
    Je = J[:, est] * core.x_scale(problem.units)[est]
    r = r.reshape(-1)
    delta = np.linalg.lstsq(Je, -r, rcond=None)[0]
    sigma2 = float(np.sum((r + Je @ delta) ** 2)) / max(readings - est.size, 1)
    return _weakest(Je, sigma2) > EARLY_MARGIN * NOISE_DOMINATED


def few_readings(cal: core.Calibration) -> bool:
    """Fewer than FEW_READINGS readings (weighted residual components of the samples used) per parameter of
    the base-set fit (robot and device)."""
    p = cal.problem
    return int(np.sum(p.w[p.used] != 0)) < FEW_READINGS * len(cal.estimated)


def fold_index(n: int, folds: int, seed: int = 0) -> np.ndarray:
    """Fold (0..folds-1) of each of n samples, balanced and shuffled."""
    return np.random.default_rng(seed).permutation(n) % folds


def fold_score(J, r, held, z, z_ref, lam: float) -> float:
    """Held-out weighted sum of squares |r_h + J_h delta|^2 of one fold, delta the Gauss-Newton step from z that
    solves the fold's training rows t (the rows not `held`) with the bias, min |r_t + J_t delta|^2 + lam |z + delta -
    z_ref|^2 (least squares on the stacked rows, so a rank-deficient J_t at lam = 0 takes the least-norm step).
    J (rows, K), r (rows,): the weighted data Jacobian in typical-size units and the residual at z, the solution of
    the same problem on every row; held: (rows,) bool."""
    train = ~held
    A = np.concatenate([J[train], np.sqrt(lam) * np.eye(J.shape[1])])
    b = -np.concatenate([r[train], np.sqrt(lam) * (z - z_ref)])
    delta = np.linalg.lstsq(A, b, rcond=None)[0]
    return float(np.sum((r[held] + J[held] @ delta) ** 2))


def heldout_scores(problem: core.Problem, cal: core.Calibration, settings: core.Settings, path=BIAS_PATH,
                   folds: int = BIAS_FOLDS, seed: int = 0, patience: int = PATIENCE) -> tuple[np.ndarray, list]:
    """(scores, stages): the pooled held-out weighted sum of squares after each stage of `path` (NaN for the stages
    not run), and the solutions of the stages run on all samples (`core.Solution`, the stages `core.calibrate`
    runs for the same schedule: its `stages`).

    The path is solved once, on all samples, from the frames-only start (each stage from the last, biased toward
    the start, as `core.calibrate` runs it). Each fold's estimate at a stage is one Gauss-Newton step from that
    stage's solution with the fold's samples left out (`fold_score`: the approximate leave-fold-out estimate; the
    stage's solution is the optimum of all folds together, so the step is short and the linearisation holds),
    scored on the samples left out. Each fold's bias is the one its own solve would have (`core.Problem.args`
    divides the weights by the RMS weighted residual of the fold's training samples at the start). Solving each
    fold's path instead (the rule before 2026-11-27) gave the same choice on every case compared (docs/delta.md);
    the pooled scores agreed to 0.01-1.2 %, at 4 x the solves (Delta, 125 positions: 20 fold solves, 2.0 s of a 2.6 s
    identify). The path stops once the score has risen for `patience` stages in a row past its least: along a
    regularisation path the held-out error falls, then rises as the fit follows the noise, and the stages past
    the rise are the costly, weakly damped ones."""
    used = np.flatnonzero(problem.used)
    fold = np.full(len(problem.q), -1)
    fold[used] = fold_index(len(used), folds, seed)
    est = np.asarray(cal.estimated, int)
    scale = problem.x_scale[est]
    r0 = np.asarray(problem.residuals(cal.x_frames))
    m = r0.shape[1]
    row_fold = np.repeat(fold, m)
    bias_unit = [np.mean(r0[problem.used & (fold != b)] ** 2) for b in range(folds)]  # `Problem.args`' scaling
    scores, stages, x = np.full(len(path), np.nan), [], cal.x_frames
    for k, mu in enumerate(path):
        sol = core.solve(problem, x, est, settings, mu, ref=cal.x_frames)
        stages.append(sol)
        x = sol.x
        J = (problem.jacobian(x) if sol.J is None else sol.J)[:, est] * scale
        r = np.asarray(problem.residuals(x)).reshape(-1)
        scores[k] = sum(fold_score(J, r, row_fold == b, x[est] / scale, cal.x_frames[est] / scale, mu * bias_unit[b])
                        for b in range(folds))
        if k - least_stage(scores[:k + 1]) >= patience:
            break
    return scores, stages


def least_stage(scores) -> int:
    """Index of the least finite score (0 when none is finite; NaN: a stage not run)."""
    scores = np.asarray(scores, float)
    return int(np.argmin(np.where(np.isfinite(scores), scores, np.inf)))


def choose_bias(problem: core.Problem, cal: core.Calibration, settings: core.Settings, path=BIAS_PATH,
                folds: int = BIAS_FOLDS, seed: int = 0) -> tuple[list[float], np.ndarray, list]:
    """(schedule, scores, stages): the prefix of `path` ending at the stage of least held-out error, the scores, and
    the solutions of that schedule's stages on all samples (`heldout_scores`)."""
    scores, stages = heldout_scores(problem, cal, settings, path, folds, seed)
    k = least_stage(scores)
    return [float(m) for m in path[:k + 1]], scores, stages[:k + 1]


__all__ = ["BIAS_FOLDS", "BIAS_PATH", "EARLY_MARGIN", "EARLY_STEPS", "FEW_READINGS", "ILL_CONDITIONED_BIAS",
           "NOISE_DOMINATED", "PATIENCE", "PRIOR_PATH", "choose_bias", "clearly_noise_dominated", "few_readings",
           "fold_index", "fold_score", "heldout_scores", "least_stage", "weakest_standard_error"]
