"""Fleet identification: one robot model calibrated from many datasets at once (docs/scale-out.md).

`identify_fleet` calibrates many robots of one model (one dataset each, same number of samples) as
one vmapped batch of the calibration core's solver (`jaxcal.fit.core.solve_batch`), sharded over
the devices JAX sees by `jaxcal.shard.over_devices`.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit import core
from jaxcal.fit.identify import identify, residual_weights, residuals
from jaxcal.shard import over_devices


@dataclasses.dataclass
class FleetResult:
    """Per robot: the full parameter vector (robot + device), convergence and position RMS (mm)."""

    names: tuple[str, ...]
    a_full: np.ndarray  # (n_robots, n_params)
    converged: np.ndarray
    iterations: np.ndarray
    rms_after: np.ndarray  # (n_robots,) position RMS of the calibrated model on its own data, mm
    estimated: tuple[str, ...]
    timings: dict


def identify_fleet(robot, datasets, devices=None, sigma_position=1e-3, sigma_orientation=1e-3, solver="lm",
                   max_steps=100, rtol=core.Settings.rtol, atol=core.Settings.atol) -> FleetResult:
    """Identify one robot model from several datasets (one per physical robot), sharded over devices.

    The estimated set and the starting point come from `identify` on the first dataset; every robot
    is then solved from there with the same model (parameters outside the estimated set stay at the
    first robot's values; the estimated ones absorb the difference, as in the base-set regrouping).
    All datasets need the same number of samples and device kind.
    """
    t0 = time.perf_counter()
    n = len(datasets[0])
    if any(len(d) != n or type(d.device) is not type(datasets[0].device) for d in datasets):
        raise ValueError("identify_fleet needs datasets of equal size and device kind")
    kw = dict(sigma_position=sigma_position, sigma_orientation=sigma_orientation)
    ref = identify(robot, datasets[0], solver=solver, max_steps=max_steps, rtol=rtol, atol=atol, **kw)
    device = datasets[0].device
    idx = np.asarray(ref.info["estimated_index"], int)
    x0 = jnp.asarray(ref.a_full)
    w = residual_weights(device, sigma_position, sigma_orientation)
    qs = np.stack([d.q for d in datasets])
    ys = np.stack([d.y for d in datasets])
    settings = core.Settings(solver, max_steps, rtol, atol)
    free = np.isin(np.arange(len(ref.names)), idx)
    # the same O(1) residual normalisation as `identify` (core.Problem.args), per robot
    problems = [core.make_problem(robot, device, q, y, weights=w, free=free, a_ref=np.asarray(ref.a_full)) for q, y in zip(qs, ys)]
    all_args = [p.args(idx, 0.0, np.asarray(ref.a_full)) for p in problems]
    x0 = jnp.asarray(ref.a_full)
    mask = np.asarray(all_args[0]["mask"])
    n_dev = 1 if devices is not None and len(devices) <= 1 else len(jax.devices() if devices is None else devices)
    pad = (-len(datasets)) % n_dev
    batched = {k: np.stack([np.asarray(a[k]) for a in all_args + all_args[:pad]]) for k in ("q", "y", "w")}
    shared = {k: v for k, v in all_args[0].items() if k not in batched}

    def solve_fleet(b, sh):
        return core.solve_batch(problems[0], x0, dict(sh, **b), settings, ("q", "y", "w"))[:4]

    t1 = time.perf_counter()
    x, ok, steps, _ = over_devices(solve_fleet, batched, shared, devices)
    run_s = time.perf_counter() - t1
    x, ok, steps = x[: len(datasets)], ok[: len(datasets)], steps[: len(datasets)]
    x = np.where(mask > 0, x, np.asarray(x0))
    unit_w = residual_weights(device, 1.0, 1.0)
    rms = []
    for a, q, y in zip(x, qs, ys):
        pe, _ = device.split_errors(residuals(robot, device, jnp.asarray(a), jnp.asarray(q), jnp.asarray(y), unit_w))
        rms.append(float(np.sqrt(np.mean(np.asarray(pe) ** 2)) * 1e3))
    return FleetResult(ref.names, x, ok, steps, np.array(rms), ref.estimated,
                       {"reference_fit_s": t1 - t0, "fleet_s (compile + run)": run_s, "devices": n_dev})


__all__ = ["FleetResult", "identify_fleet", "over_devices"]
