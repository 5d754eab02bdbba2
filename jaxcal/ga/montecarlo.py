"""Monte Carlo loops around the GA (seed 000 §5.3, Figure 5.2).

Level 1: repeat the GA on one set of configurations, in vmapped batches of runs, and stop when
the running mean of the identified errors (eq 5.8-5.9: mean_k = (mean_{k-1} (k-1) + dg_k) / k)
changes by less than a tolerance L1 (eq 5.7: max_i |mean_k,i - mean_{k-1},i| < L1).
Level 2: repeat level 1 over m sets of random configurations (uniform within the joint bounds).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxcal.fit.simulate import random_configurations, simulate
from jaxcal.ga.runner import run


def running_means(samples):
    """Running means (eq 5.8-5.9) of samples (K, n): row k is the mean of rows 0..k."""
    s = np.asarray(samples, float)
    return np.cumsum(s, axis=0) / np.arange(1, len(s) + 1)[:, None]


def stopping_index(samples, tol, min_runs=2):
    """Number of runs k after which the running mean first changes by less than tol (eq 5.7),
    or None if it never does."""
    means = running_means(samples)
    change = np.max(np.abs(np.diff(means, axis=0)), axis=1)  # change[k-2]: from k-1 runs to k runs
    for k in range(max(min_runs, 2), len(means) + 1):
        if change[k - 2] < tol:
            return k
    return None


@dataclasses.dataclass
class Level1Result:
    mean: np.ndarray          # (n_free,) mean identified errors over the runs used
    std: np.ndarray           # (n_free,) standard deviation per parameter
    runs: int                 # runs used (stopping rule) or all runs done
    stopped: bool             # whether eq 5.7 was met
    dg: np.ndarray            # (runs, n_free) identified errors of each run
    fitness: np.ndarray       # (runs,) final best cost of each run
    running_mean: np.ndarray  # (runs, n_free) convergence pattern (Figure 6.11)
    free: tuple
    timings: dict


def level1(robot, data, *, tol=1e-5, batch=10, max_runs=50, min_runs=2, seed=0, **ga_kw):
    """Level-1 Monte Carlo: GA batches of `batch` vmapped runs until eq 5.7 holds (or max_runs)."""
    dgs, fits, names, t_run, t_comp = [], [], None, 0.0, 0.0
    k_stop = None
    b = 0
    while sum(len(d) for d in dgs) < max_runs:
        res = run(robot, data, seed=seed + 1000 * b, runs=batch, **ga_kw)
        dgs.append(res.runs_dg)
        fits.append(res.runs_fitness)
        names = res.free
        t_run += res.timings["run_s"]
        t_comp += res.timings["compile_s"]
        b += 1
        k_stop = stopping_index(np.concatenate(dgs), tol, min_runs)
        if k_stop is not None:
            break
    dg = np.concatenate(dgs)[: k_stop or max_runs]
    return Level1Result(mean=dg.mean(0), std=dg.std(0, ddof=1) if len(dg) > 1 else np.zeros(dg.shape[1]),
                        runs=len(dg), stopped=k_stop is not None, dg=dg, fitness=np.concatenate(fits)[: len(dg)],
                        running_mean=running_means(dg), free=names, timings={"run_s": t_run, "compile_s": t_comp})


@dataclasses.dataclass
class Level2Result:
    means: np.ndarray      # (m, n_free) level-1 means, one row per configuration set
    stds: np.ndarray       # (m, n_free)
    spread: np.ndarray     # (n_free,) standard deviation of the means across configuration sets
    level1: list
    free: tuple


def level2(robot, a_true, device, *, m=5, n_configurations=8, noise=None, seed=0, device_params=None, **level1_kw):
    """Level-2 Monte Carlo: level 1 on m random configuration sets (uniform within joint bounds),
    measurements simulated from a_true; the stability of the means across sets (Figure 6.12)."""
    results = []
    for j in range(m):
        q = random_configurations(robot, n_configurations, seed=seed + j)
        data = simulate(robot, a_true, q, device, noise=noise, device_params=device_params, seed=seed + 100 + j)
        results.append(level1(robot, data, seed=seed + 10_000 * (j + 1), device_params=device_params, **level1_kw))
    means = np.stack([r.mean for r in results])
    return Level2Result(means=means, stds=np.stack([r.std for r in results]), spread=means.std(0, ddof=1) if m > 1 else np.zeros(means.shape[1]),
                        level1=results, free=results[0].free)
