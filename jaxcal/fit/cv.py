"""k-fold cross-validation of any robot on any dataset, through `identify` (hence the calibration core).

`cross_validate(robot, data, folds=5)` splits the samples into k folds (repeated poses, i.e. identical
joint readings, stay in one fold so a held-out pose is never seen in training), calibrates on the other
k - 1 folds each time and scores the held-out fold, for the calibrated model and for the fair "before"
(nominal robot, device frame and marker fitted on the same training samples). Each training set is a
sample-weight mask over the whole dataset, so every fold shares one compiled solver.
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
    for b in range(folds):
        weights = (fold != b).astype(float)
        fit = identify(robot, data, sample_weights=weights, **identify_kw)
        frames = identify(robot, data, sample_weights=weights, **dict(identify_kw, free=()))
        test = data.subset(np.flatnonzero(fold == b))
        (pb, ob), (pa, oa) = frames.errors(test), fit.errors(test)
        held_b.append(pb if pb is not None else ob)
        held_a.append(pa if pa is not None else oa)
        if pb is not None and ob is not None:
            ori_b.append(ob)
            ori_a.append(oa)
        healthy += bool(fit.health.ok)
        rows.append({"fold": b, "samples": int(np.sum(fold == b)), "heldout_before": _rms(held_b[-1]),
                     "heldout_after": _rms(held_a[-1]), "converged": bool(fit.converged), "warnings": list(fit.health.warnings)})
    cat = lambda parts: np.concatenate(parts) if parts else None  # noqa: E731
    return CVResult(folds, _rms(cat(held_b)), _rms(cat(held_a)), _rms(cat(ori_b)), _rms(cat(ori_a)), tuple(rows), healthy,
                    {"total_s": time.perf_counter() - t0})


__all__ = ["CVResult", "cross_validate", "fold_of_samples"]
