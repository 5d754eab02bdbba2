"""k-fold cross-validation of any robot on any dataset, through `identify` (hence the calibration core).

`cross_validate(robot, data, folds=5)` splits the samples into k folds (repeated poses, i.e. identical
joint readings, stay in one fold so a held-out pose is never seen in training), calibrates on the other
k - 1 folds each time and scores the held-out fold, for the calibrated model and for the fair "before"
(nominal robot, device frame and marker fitted on the same training samples). Each training set is a
sample-weight mask over the whole dataset, so every fold shares one compiled solver.

`nested_cross_validate(robot, data, candidates)` makes every modelling choice (a named set of `identify`
options) per outer fold by an inner k-fold cross-validation on that fold's training samples only, then scores
the chosen candidate on the outer held-out fold: an honest estimate of what choosing by cross-validation
gains, to set against a fixed default (docs/defaults.md).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from jaxcal.fit.data import Dataset
from jaxcal.fit.identify import identify


def fold_of_samples(q, folds: int, seed: int = 0) -> np.ndarray:
    """Fold index (0..folds-1) of every sample; identical joint readings share a fold."""
    q = np.asarray(q, float)
    _, groups = np.unique(np.round(q, 9), axis=0, return_inverse=True)
    groups = groups.reshape(-1)
    n_groups = groups.max() + 1
    if not 2 <= folds <= n_groups:
        raise ValueError(f"folds must be between 2 and the number of distinct poses ({n_groups}), got {folds}")
    order = np.random.default_rng(seed).permutation(n_groups)
    return np.argsort(order)[groups] % folds


def _rms(e) -> float | None:
    return None if e is None else float(np.sqrt(np.mean(np.asarray(e) ** 2)) * 1e3)


@dataclasses.dataclass(frozen=True)
class CVResult:
    """Held-out RMS pooled over every held-out sample (position mm; orientation mrad, or the device's error
    unit when it has no position), before (frames only) and after calibration, per fold and pooled."""

    folds: int
    heldout_before: float
    heldout_after: float
    heldout_orientation_before: float | None
    heldout_orientation_after: float | None
    per_fold: tuple[dict, ...]
    healthy_folds: int  # folds whose fit has no health warning
    timings: dict
    heldout_errors: tuple = ()  # per-sample held-out error after calibration (m or rad), in sample order

    def report(self) -> str:
        o = ""
        if self.heldout_orientation_after is not None and self.heldout_orientation_before is not None:
            o = f"; orientation {self.heldout_orientation_before:.4g} -> {self.heldout_orientation_after:.4g} mrad"
        return (f"{self.folds}-fold cross-validation: held-out RMS {self.heldout_before:.4g} -> {self.heldout_after:.4g} "
                f"(frames only -> calibrated){o}; {self.healthy_folds} of {self.folds} fits without health warnings")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def cross_validate(robot, data: Dataset, folds: int = 5, seed: int = 0, **identify_kw) -> CVResult:
    """k-fold cross-validation of `identify(robot, train, **identify_kw)` on `data` (see the module docstring)."""
    t0 = time.perf_counter()
    fold = fold_of_samples(data.q, folds, seed)
    held_b, held_a, ori_b, ori_a, rows, healthy = [], [], [], [], [], 0
    per_sample = np.zeros(len(data))
    for b in range(folds):
        weights = (fold != b).astype(float)
        fit = identify(robot, data, sample_weights=weights, **identify_kw)
        frames = identify(robot, data, sample_weights=weights, **dict(identify_kw, free=()))
        test = data.subset(np.flatnonzero(fold == b))
        (pb, ob), (pa, oa) = frames.errors(test), fit.errors(test)
        held_b.append(pb if pb is not None else ob)
        held_a.append(pa if pa is not None else oa)
        per_sample[fold == b] = held_a[-1]
        if pb is not None and ob is not None:
            ori_b.append(ob)
            ori_a.append(oa)
        healthy += bool(fit.health.ok)
        rows.append({"fold": b, "samples": int(np.sum(fold == b)), "heldout_before": _rms(held_b[-1]),
                     "heldout_after": _rms(held_a[-1]), "converged": bool(fit.converged), "warnings": list(fit.health.warnings)})
    cat = lambda parts: np.concatenate(parts) if parts else None  # noqa: E731
    return CVResult(folds, _rms(cat(held_b)), _rms(cat(held_a)), _rms(cat(ori_b)), _rms(cat(ori_a)), tuple(rows), healthy,
                    {"total_s": time.perf_counter() - t0}, tuple(per_sample.tolist()))


def _heldout_error(fit, data: Dataset, test_mask) -> np.ndarray:
    """Per-sample error of a fit (position m, or the device's own error) on the samples of test_mask."""
    pe, oe = fit.errors(data.subset(np.flatnonzero(test_mask)))
    return pe if pe is not None else oe


def _fit(robot, data: Dataset, train_mask, options: dict, common: dict):
    return identify(robot, data, sample_weights=train_mask.astype(float), **(common | options))


def inner_scores(robot, data: Dataset, candidates: dict, train_mask, inner_folds: int = 4, seed: int = 1,
                 **common) -> dict:
    """Pooled inner cross-validated RMS (mm or mrad) of every candidate, using the samples of train_mask only."""
    train = np.flatnonzero(train_mask)
    inner = fold_of_samples(data.q[train], inner_folds, seed)
    scores = {}
    for label, options in candidates.items():
        errors = []
        for b in range(inner_folds):
            fit_mask = np.zeros(len(data), bool)
            fit_mask[train[inner != b]] = True
            test_mask = np.zeros(len(data), bool)
            test_mask[train[inner == b]] = True
            errors.append(_heldout_error(_fit(robot, data, fit_mask, options, common), data, test_mask))
        scores[label] = _rms(np.concatenate(errors))
    return scores


@dataclasses.dataclass(frozen=True)
class NestedCVResult:
    """Held-out RMS of the candidate chosen per outer fold by inner cross-validation (pooled over every
    held-out sample), the choice and inner scores per fold, and the per-sample held-out errors."""

    folds: int
    heldout: float
    chosen: tuple[str, ...]
    inner: tuple[dict, ...]
    converged: tuple[bool, ...]  # the chosen candidate's outer fit, per fold
    heldout_errors: tuple
    timings: dict

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def nested_cross_validate(robot, data: Dataset, candidates: dict, folds: int = 5, inner_folds: int = 4, seed: int = 0,
                          **common) -> NestedCVResult:
    """Nested k-fold cross-validation: per outer fold (the folds of `cross_validate` with this seed), the
    candidate (label -> `identify` options, fixed before any fit) with the smallest inner cross-validated RMS on
    the training samples (`inner_scores`) is fitted on them and scored on the held-out fold, which no choice
    ever sees. `common`: options every candidate shares (e.g. sigma_position)."""
    if not candidates:
        raise ValueError("nested_cross_validate needs at least one candidate")
    t0 = time.perf_counter()
    fold = fold_of_samples(data.q, folds, seed)
    per_sample = np.zeros(len(data))
    chosen, inner, converged = [], [], []
    for b in range(folds):
        train_mask = fold != b
        scores = inner_scores(robot, data, candidates, train_mask, inner_folds, seed + 1, **common)
        best = min(scores, key=scores.get)
        fit = _fit(robot, data, train_mask, candidates[best], common)
        per_sample[fold == b] = _heldout_error(fit, data, fold == b)
        chosen.append(best)
        inner.append(scores)
        converged.append(bool(fit.converged))
    return NestedCVResult(folds, _rms(per_sample), tuple(chosen), tuple(inner), tuple(converged),
                          tuple(per_sample.tolist()), {"total_s": time.perf_counter() - t0})


__all__ = ["CVResult", "NestedCVResult", "cross_validate", "fold_of_samples", "inner_scores", "nested_cross_validate"]
