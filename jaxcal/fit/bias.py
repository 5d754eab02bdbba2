"""The bias term chosen by held-out error (seed 004 eq 3.12, §3.3; §4.3 Delta simulation 3).

The thesis adds mu ||a - a0||^2 to the cost and lowers mu stage by stage. Ending at mu = 0 is right for a
well-determined problem; for a noise-dominated one (theodolite angles from 3.7 m on the Delta: linearised
standard errors of several estimated parameters far above 1 mm) the last stages fit the noise along weak
directions and the calibrated model
predicts new settings worse than the nominal one. `choose_bias` picks where the schedule stops by
k-fold cross-validation over the samples: each fold's training set (a weight mask, so one compiled
solver serves every fold) is fitted along the path BIAS_PATH from the same frames-only start, every stage
is scored on the held-out samples (weighted residual sum of squares), and the stage with the lowest
pooled held-out score wins (`identify(bias="heldout")`, and `identify`'s default for a noise-dominated closed
mechanism). On Delta simulation 3's seed-0 draw the fixed ILL_CONDITIONED_BIAS predicted new tool positions
better (worst 0.95 mm against 1.79 mm), but over six noise draws it reached 8.05 mm where the k-fold choice
stayed below 1.8 mm (docs/delta.md); the k-fold path costs up to 24 solves, fewer once the held-out score has
risen past its least by more than the share RISE (PATIENCE such stages; the later stages are not run). Open chains
keep ILL_CONDITIONED_BIAS.
"""

from __future__ import annotations

import concurrent.futures
import os

import jax
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
# The path stops at the first PATIENCE stages whose pooled held-out score exceeds the least so far by more than the
# share RISE (`heldout_scores`). Chosen on 36 simulated cases and checked on 37 others (Delta from 60 and 125 positions
# at 0.01-0.1 mm noise and by theodolite, Kiwibot, TALOS arms from 20 positions; the whole path run on each:
# benchmarks/bias_patience.py): on the first 36, one rise of any size (PATIENCE 1, RISE 0) chose another stage than
# two rises once (a rise of 1e-4 of the score, then a lower score: new tool positions 0.066 against 0.063 mm); one rise
# by more than 1e-3 to 1e-2 of the score chose as two rises on all 73 (RISE 5e-3: 256 stages run against 314; 255
# with PATIENCE + 1 stages past the least as a bound, the rule before, so that a flat score runs no more). The
# benchmark's Delta (125 positions) no longer runs the stage at 1e-6, 72 of its call's 184 LM steps: call 481-548 ->
# 349-371 ms.
PATIENCE = 1
RISE = 5e-3
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
# far from its optimum (its residual not yet down to the noise) goes on. 10 steps (20 until the eighteenth session):
# on 15 cases (the three real datasets, simulated UR10 / Stanford / TALOS arms from 20 and 60 positions, the Delta from
# 125 positions at 0, 0.01 and 0.1 mm noise) the rule and the estimate were the same bit for bit at 10 as at 20 (the
# noise-free Delta, 70 steps, was not stopped at 10); the Delta's call 547 -> 523 ms (docs/benchmarks.md).
EARLY_STEPS = 10
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
    r = cal.residuals[p.used]
    sigma2 = float(np.sum(r**2)) / max(r.size - est.size, 1)
    return _weakest(cal.R[:, est] * core.x_scale(p.units)[est], sigma2)  # R^T R = J^T J


def clearly_noise_dominated(problem: core.Problem, x, J, estimated, r=None) -> bool:
    """Whether an unconverged fit at x (J: the weighted data Jacobian there; r: the weighted residuals there, when the
    caller has them) is noise-dominated by EARLY_MARGIN: `weakest_standard_error` with sigma^2 from min over delta of
    |r + J_e delta|^2 (the cost the linearised fit reaches; below the cost at x, so the test errs toward going on with
    the fit)."""
    est = np.asarray(estimated, int)
    if not est.size:
        return False
    r = np.asarray(problem.residuals(x) if r is None else r)
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


def heldout_scores(problem: core.Problem, cal: core.Calibration, settings: core.Settings, path=BIAS_PATH,
                   folds: int = BIAS_FOLDS, seed: int = 0, patience: int = PATIENCE,
                   rise: float = RISE) -> tuple[np.ndarray, int, int]:
    """(scores, unconverged, solves): the pooled held-out weighted sum of squares after each stage of `path` (one row
    per stage), stage by stage over the folds; the path stops once `patience` stages past the least score exceed it
    by more than the share `rise` (`risen`; NaN for the stages not run: along a regularisation path the held-out
    error falls, then rises as the fit follows the noise, and the stages past the rise are the costly, weakly damped
    ones; a rise within `rise` of the least is not counted, the score may fall again after it), and in any case
    `patience` + 1 stages past the least (a flat score runs no more stages than two rises of any size did).
    unconverged: how many of the `solves` fold solves stopped at the step limit (a score from such a fit is not the
    fold's optimum's: on a Delta seen from 2.6 m through 0.2 mm noise, weakest standard error 282 x the typical size,
    every fold solve stopped at the gap baselines' 40 steps, and solved from another start the folds chose another
    stage)."""
    used = np.flatnonzero(problem.used)
    fold = np.full(len(problem.q), -1)
    fold[used] = fold_index(len(used), folds, seed)
    held = [fold == b for b in range(folds)]
    trains = [problem.with_weights(problem.w * (~h)[:, None]) for h in held]
    xs = [cal.x_frames] * folds
    whole = None if cal.r0 is None else (cal.r0, cal.J0)
    reads = [core.reweighted(whole, problem.w, t.w) for t in trains]  # each fold's (r, J) at its start: `core.solve`'s
    at_frames = [None if read is None else read[0] for read in reads]  # each fold's residuals at its prior (the start)
    scores = np.full(len(path), np.nan)

    unconverged = solves = 0

    def stage(b: int, mu: float) -> tuple[np.ndarray, tuple | None, float, bool]:  # fold b's next stage, its held-out score
        sol = core.solve(trains[b], xs[b], cal.estimated, settings, mu, ref=cal.x_frames, start=reads[b],
                         ref_residuals=at_frames[b])
        r = trains[b].with_weights(problem.w * held[b][:, None]).residuals(sol.x)  # held-out samples, the fits' shape
        return sol.x, sol.read, float(np.sum(np.asarray(r) ** 2)), bool(sol.converged)

    with concurrent.futures.ThreadPoolExecutor(fold_workers(folds)) as pool:
        for k, mu in enumerate(path):
            xs, reads, held_out, converged = zip(*pool.map(stage, range(folds), [mu] * folds))
            scores[k] = sum(held_out)  # in fold order: the same sum as one fold after another
            unconverged, solves = unconverged + converged.count(False), solves + folds
            if path_ends(scores[:k + 1], patience, rise):
                break
    return scores, unconverged, solves


def fold_workers(folds: int) -> int:
    """Threads for the folds' solves: one per CPU core, at most one per fold, on the CPU backend (1 elsewhere: an
    accelerator runs one program at a time, and a thread would not see the caller's `jax.default_device` context).
    The folds are independent, and a compiled solve runs outside the GIL (Delta, 125 positions, 2 cores: a stage's
    four fold solves 1.7-2.7x faster, the same estimates bit for bit)."""
    if jax.default_backend() != "cpu":
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(folds, cores))


def least_stage(scores) -> int:
    """Index of the least finite score (0 when none is finite; NaN: a stage not run)."""
    scores = np.asarray(scores, float)
    return int(np.argmin(np.where(np.isfinite(scores), scores, np.inf)))


def risen(scores, rise: float) -> int:
    """How many stages after the least score (`least_stage`) exceed it by more than the share `rise`, or have none
    (a fit whose held-out score is not finite)."""
    scores = np.asarray(scores, float)
    k = least_stage(scores)
    return int(np.sum(~(scores[k + 1:] <= scores[k] * (1.0 + rise))))


def path_ends(scores, patience: int = PATIENCE, rise: float = RISE) -> bool:
    """Whether the path stops after the stages scored so far (`heldout_scores`): `patience` of them past the least
    exceed it by more than the share `rise` (`risen`), or more than `patience` lie past the least."""
    return risen(scores, rise) >= patience or len(scores) - 1 - least_stage(scores) > patience


def choose_bias(problem: core.Problem, cal: core.Calibration, settings: core.Settings, path=BIAS_PATH,
                folds: int = BIAS_FOLDS, seed: int = 0) -> tuple[list[float], np.ndarray, dict]:
    """(schedule, scores, record): the prefix of `path` ending at the stage of least held-out error, the scores, and
    {"bias_fold_solves": how many, "bias_fold_solves_unconverged": how many stopped at the step limit} (`heldout_scores`)."""
    scores, unconverged, solves = heldout_scores(problem, cal, settings, path, folds, seed)
    k = least_stage(scores)
    return [float(m) for m in path[:k + 1]], scores, {"bias_fold_solves": solves, "bias_fold_solves_unconverged": unconverged}


__all__ = ["BIAS_FOLDS", "BIAS_PATH", "EARLY_MARGIN", "EARLY_STEPS", "FEW_READINGS", "ILL_CONDITIONED_BIAS",
           "NOISE_DOMINATED", "PATIENCE", "PRIOR_PATH", "RISE", "choose_bias", "clearly_noise_dominated", "few_readings",
           "fold_index", "fold_workers", "heldout_scores", "least_stage", "path_ends", "risen",
           "weakest_standard_error"]
