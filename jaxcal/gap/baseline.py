"""The diagnosis baseline: the geometric calibration of every training fold, by the calibration core.

A fold is a sample-weight mask, so fold b's baseline is exactly `identify` on that fold's samples
(same start: device frame registered onto the readings, then the frames-only fit; same base set;
same solver; same bias rule: `calibrate_with_default_bias`), and the all-data baseline is `identify` on
every sample.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses

import numpy as np

from jaxcal.fit import core
from jaxcal.fit.bias import fold_workers
from jaxcal.fit.identify import calibrate_with_default_bias, residual_weights


def baseline_fits(robot, data, train_masks, *, sigma_position: float, sigma_orientation: float,
                  max_steps: int | None = None, settings: core.Settings | None = None) -> list[core.Calibration]:
    """One `core.Calibration` per boolean mask of training samples (N,), as `identify(robot, data.subset(mask),
    sigma_position=, sigma_orientation=, max_steps=)` would give (settings: the solver's; max_steps overrides
    its step limit). Samples whose loops do not close at the
    nominal parameters are left out of every fold (as `identify` leaves them out)."""
    return [cal for cal, _ in baseline_calibrations(robot, data, train_masks, sigma_position=sigma_position,
                                                    sigma_orientation=sigma_orientation, max_steps=max_steps,
                                                    settings=settings)]


def final_bias(bias_info: dict) -> float:
    """The bias mu of the last stage `calibrate_with_default_bias` ran (0 when the estimate was not noise-dominated)."""
    schedule = bias_info.get("bias_schedule", [0.0])
    return float(schedule[-1]) if len(schedule) else 0.0


def baseline_calibrations(robot, data, train_masks, *, sigma_position: float, sigma_orientation: float,
                          max_steps: int | None = None, settings: core.Settings | None = None) -> list[tuple]:
    """`baseline_fits` with each fit's record of identify's bias rule: [(calibration, bias record)]."""
    device = data.device
    closes = core.drop_unclosed(robot, robot.nominal, data.q)
    problem = core.make_problem(robot, device, data.q, data.y,
                                weights=residual_weights(device, sigma_position, sigma_orientation),
                                free=np.concatenate([robot.free_mask, device.free_mask]),
                                a_ref=np.concatenate([robot.nominal_np, device.nominal_np]))
    settings = settings or core.Settings()
    if max_steps is not None:
        settings = dataclasses.replace(settings, max_steps=max_steps)

    def fit(mask):
        return calibrate_with_default_bias(problem.with_weights(problem.w * (np.asarray(mask) & closes)[:, None]), settings)

    if not len(train_masks):
        return []
    first = fit(train_masks[0])  # alone: it compiles the programs that every fold shares (same shapes)
    with concurrent.futures.ThreadPoolExecutor(fold_workers(len(train_masks) - 1)) as pool:  # independent folds
        return [first] + list(pool.map(fit, train_masks[1:]))


__all__ = ["baseline_calibrations", "baseline_fits", "final_bias"]
