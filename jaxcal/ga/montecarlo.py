"""Monte Carlo loops around the GA (seed 000 §5.3, Figure 5.2).

Level 1: repeat the GA on one set of configurations, in vmapped batches of runs, and stop when
the running mean (eq 5.8-5.9: mean_k = (mean_{k-1} (k-1) + x_k) / k) changes by less than a
tolerance L1 (eq 5.7: max_i |mean_k,i - mean_{k-1},i| < L1). The rule is applied either to the
identified errors dg themselves (`stop_on="parameters"`, the seed's choice) or to the tip
positions the identified robot predicts at fixed check configurations (`stop_on="tip"`). With
redundant parameters (MRR-1's 18 PRY parameters: see `jc.identifiable`) each run lands at a
different point of the solution set, so the running mean of dg keeps wandering (MRR-1, 50 x 250:
still changing by 5-9e-5 per run after 40-50 runs, measured); the predicted positions are
identifiable and their running mean settles (changes 8.9e-6, 3.2e-6, ... 8.4e-7 m after 2..8
runs, measured), so "tip" is the rule to use for redundant models and the default.
Level 2 (loop 3): repeat level 1 over random configuration sets (uniform within the joint bounds),
m sets per round vmapped (every batch of GA runs is one compiled call for the round's sets), adding
rounds until the running global mean over sets (eq 5.10) settles by eq 5.7.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit.simulate import random_configurations, simulate
from jaxcal.forward import forward
from jaxcal.ga import core, runner

STOP_ON = ("parameters", "tip")
DEFAULT_TOL = {"parameters": 1e-5, "tip": 1e-6}  # L1 of eq 5.7: the seed's 1e-5 on dg; 1e-6 m on tip positions


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
    running_mean: np.ndarray  # (runs, n_free) convergence pattern of dg (Figure 6.11)
    free: tuple
    timings: dict
    stop_on: str = "parameters"
    samples: np.ndarray | None = None  # (runs, k) the quantity eq 5.7 was applied to (dg, or tip positions (m))


def tip_samples(robot, setup, dg, check_q):
    """Tip positions (runs, K * 3) predicted at check_q by each run's identified robot."""
    idx = jnp.asarray(setup.free_idx)

    def one(d):
        a = setup.a_full0.at[idx].add(d)[: robot.n_params]
        return forward(robot, a, check_q).p.reshape(-1)

    return np.asarray(jax.vmap(one)(jnp.asarray(dg)))


def _samples(robot, setup, dg, stop_on, check_q):
    return np.asarray(dg) if stop_on == "parameters" else tip_samples(robot, setup, dg, check_q)


def _level1_result(dg, fits, samples, tol, min_runs, max_runs, names, timings, stop_on):
    k_stop = stopping_index(samples, tol, min_runs)
    n = k_stop or min(max_runs, len(dg))
    dg = dg[:n]
    return Level1Result(mean=dg.mean(0), std=dg.std(0, ddof=1) if n > 1 else np.zeros(dg.shape[1]), runs=n,
                        stopped=k_stop is not None, dg=dg, fitness=fits[:n], running_mean=running_means(dg), free=names,
                        timings=timings, stop_on=stop_on, samples=samples[:n])


def _check(stop_on, robot, check_q):
    if stop_on not in STOP_ON:
        raise ValueError(f"stop_on must be one of {STOP_ON}, got {stop_on!r}")
    return jnp.asarray(random_configurations(robot, 10, seed=12345) if check_q is None else check_q)


def level1(robot, data, *, tol=None, batch=10, max_runs=50, min_runs=2, seed=0, stop_on="tip", check_q=None,
           **ga_kw):
    """Level-1 Monte Carlo: GA batches of `batch` vmapped runs (seeds seed + 1000 b) until eq 5.7
    holds for the chosen quantity (or max_runs). stop_on="tip" (default): tol in metres on the
    positions predicted at check_q (default 10 random configurations); "parameters": the seed's rule
    on dg, which never settles for redundant parameters. tol defaults to DEFAULT_TOL[stop_on]."""
    check_q = _check(stop_on, robot, check_q)
    tol = DEFAULT_TOL[stop_on] if tol is None else tol
    setup = runner.prepare(robot, data, **ga_kw)
    dgs, fits, samples, names, t_run, t_comp = [], [], [], None, 0.0, 0.0
    b = 0
    while sum(len(d) for d in dgs) < max_runs:
        res = runner.run(robot, data, seed=seed + 1000 * b, runs=batch, **ga_kw)
        dgs.append(res.runs_dg)
        fits.append(res.runs_fitness)
        samples.append(_samples(robot, setup, res.runs_dg, stop_on, check_q))
        names = res.free
        t_run += res.timings["run_s"]
        t_comp += res.timings["compile_s"]
        b += 1
        if stopping_index(np.concatenate(samples), tol, min_runs) is not None:
            break
    return _level1_result(np.concatenate(dgs), np.concatenate(fits), np.concatenate(samples), tol, min_runs, max_runs,
                          names, {"run_s": t_run, "compile_s": t_comp}, stop_on)


@dataclasses.dataclass
class Level2Result:
    means: np.ndarray           # (sets, n_free) level-1 means, one row per configuration set
    stds: np.ndarray            # (sets, n_free)
    spread: np.ndarray          # (n_free,) standard deviation of the means across configuration sets
    level1: list
    free: tuple
    global_mean: np.ndarray     # (n_free,) eq 5.10: the mean of the sets' level-1 means
    global_running: np.ndarray  # (sets, n_free) running global mean after 1, 2, ... sets
    global_samples: np.ndarray  # (sets, k) running global mean of the quantity the stopping rule used
    stopped: bool               # whether eq 5.7 over sets was met (else the set limit ended the loop)
    global_tol: float
    timings: dict = dataclasses.field(default_factory=dict)

    @property
    def sets(self) -> int:
        return len(self.level1)

    def stable(self, tol: float | None = None) -> np.ndarray:
        """(n_free,) bool: parameters whose running global mean moved by less than tol (default
        global_tol) when the last set was added (eq 5.7 per parameter; Figure 6.12's "stable")."""
        tol = self.global_tol if tol is None else tol
        if self.sets < 2:
            return np.zeros(self.global_mean.shape, bool)
        return np.abs(self.global_running[-1] - self.global_running[-2]) < tol


@functools.lru_cache(maxsize=16)
def _over_sets(fn, in_axes):
    """jit(vmap) of a jitted GA function's body over a leading configuration-set axis (in_axes as in vmap)."""
    return core.jit_cpu_options(jax.vmap(fn.__wrapped__, in_axes))


def run_sets(robot, datasets, seeds, runs, **ga_kw):
    """`runs` GA runs on each of the m datasets (same shapes) in one compiled call per chunk, vmapped
    over the sets; set j uses the keys of runner.run(seed=seeds[j], runs=runs), so its runs equal
    the ones runner.run gives. Returns (dg (m, runs, n_free), cost (m, runs), setup, timings)."""
    setups = [runner.prepare(robot, d, **ga_kw) for d in datasets]
    st = setups[0]
    if st.start is not None:
        raise ValueError("run_sets starts from random populations; `initial` is not supported")
    payload = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[s.payload for s in setups])
    keys = jnp.stack([jax.random.split(jax.random.PRNGKey(int(s)), runs) for s in seeds])
    t0 = time.perf_counter()
    init = runner.compiled_for_shapes(_over_sets(st.init_random, (0, 0, None, None)), keys, payload, st.lb, st.ub)
    state = init(keys, payload, st.lb, st.ub)
    chunk = runner.compiled_for_shapes(_over_sets(st.chunk_fn, (0, 0, None, None)), state, payload, st.lb, st.ub)
    best = runner.compiled_for_shapes(_over_sets(st.best_fn, 0), state)
    jax.block_until_ready(state)
    t1 = time.perf_counter()
    for _ in range(st.opts.generations // st.chunk):
        state, _, _ = chunk(state, payload, st.lb, st.ub)
    dg, cost = best(state)
    jax.block_until_ready(dg)
    return np.asarray(dg), np.asarray(cost), st, {"compile_s": t1 - t0, "run_s": time.perf_counter() - t1}


def _datasets(robot, a_true, device, first, count, n_configurations, noise, seed, device_params):
    """Measurements simulated from a_true on configuration sets first .. first + count - 1 (set j:
    n_configurations uniform random configurations of seed + j, noise seed + 100 + j)."""
    out = []
    for j in range(first, first + count):
        q = random_configurations(robot, n_configurations, seed=seed + j)
        out.append(simulate(robot, a_true, q, device, noise=noise, device_params=device_params, seed=seed + 100 + j))
    return out


def _level1_vmapped(robot, datasets, set_seeds, *, tol, batch, max_runs, min_runs, stop_on, check_q, device_params,
                    **ga_kw):
    """Level 1 on every dataset, each batch of GA runs one vmapped call for all sets, until every set
    has met eq 5.7 or max_runs. Returns (Level1Result per set, timings)."""
    dgs, fits, samples, timings = [], [], [], {"run_s": 0.0, "compile_s": 0.0}
    b = 0
    while b * batch < max_runs:
        dg, cost, st, t = run_sets(robot, datasets, [s + 1000 * b for s in set_seeds], batch, device_params=device_params,
                                   **ga_kw)
        dgs.append(dg)
        fits.append(cost)
        samples.append(np.stack([_samples(robot, st, d, stop_on, check_q) for d in dg]))
        timings = {k: timings[k] + t[k] for k in timings}
        b += 1
        if all(stopping_index(s, tol, min_runs) is not None for s in np.concatenate(samples, axis=1)):
            break
    dg, fit, smp = np.concatenate(dgs, axis=1), np.concatenate(fits, axis=1), np.concatenate(samples, axis=1)
    names = tuple(st.names[i] for i in st.free_idx)
    per_set_timing = {k: v / len(datasets) for k, v in timings.items()}
    results = [_level1_result(dg[j], fit[j], smp[j], tol, min_runs, max_runs, names, per_set_timing, stop_on)
               for j in range(len(datasets))]
    return results, timings


def level2(robot, a_true, device, *, m=8, max_sets=None, global_tol=None, n_configurations=1, noise=None, seed=0,
           device_params=None, tol=None, batch=10, max_runs=50, min_runs=2, stop_on="tip", check_q=None,
           vectorized=True, **ga_kw):
    """Level-2 Monte Carlo (loop 3 of Figure 5.2, eq 5.10): level 1 on random configuration sets
    (n_configurations configurations uniform within the joint bounds; the seed uses one), added m sets
    per round, until the running global mean over sets, Delta g_global = sum_j mean_j / k (eq 5.10),
    changes by less than global_tol when set k is added (eq 5.7 over sets, applied to the same
    quantity as level 1: `stop_on`), or max_sets sets (default 4 m) are done. The result keeps the
    first k sets (k the stopping set, or all). Measurements are simulated from a_true.

    vectorized=True runs each batch of level 1 for all m sets of a round in one vmapped call (until
    every set has met eq 5.7 or max_runs); False loops over the sets with `level1` (the same runs).
    tol / global_tol default to DEFAULT_TOL[stop_on]."""
    check_q = _check(stop_on, robot, check_q)
    tol = DEFAULT_TOL[stop_on] if tol is None else tol
    global_tol = tol if global_tol is None else global_tol
    max_sets = 4 * m if max_sets is None else max_sets
    kw = dict(tol=tol, batch=batch, max_runs=max_runs, min_runs=min_runs, stop_on=stop_on, check_q=check_q)
    results, timings, t0 = [], {"run_s": 0.0, "compile_s": 0.0}, time.perf_counter()
    while len(results) < max_sets:
        first, count = len(results), min(m, max_sets - len(results))
        datasets = _datasets(robot, a_true, device, first, count, n_configurations, noise, seed, device_params)
        set_seeds = [seed + 10_000 * (j + 1) for j in range(first, first + count)]
        if vectorized:
            new, t = _level1_vmapped(robot, datasets, set_seeds, device_params=device_params, **kw, **ga_kw)
        else:
            new = [level1(robot, d, seed=s, device_params=device_params, **kw, **ga_kw) for d, s in zip(datasets, set_seeds)]
            t = {k: sum(r.timings[k] for r in new) for k in timings}
        results += new
        timings = {k: timings[k] + t[k] for k in timings}
        if stopping_index(_set_means(results), global_tol) is not None:
            break
    k_stop = stopping_index(_set_means(results), global_tol)
    timings["wall_s"] = time.perf_counter() - t0
    return _level2_result(results[:k_stop] if k_stop else results, k_stop is not None, global_tol, timings)


def _set_means(results):
    """(sets, k): each set's level-1 mean of the quantity its stopping rule used (dg or tip positions)."""
    return np.stack([r.samples.mean(0) for r in results])


def _level2_result(results, stopped, global_tol, timings):
    means = np.stack([r.mean for r in results])
    spread = means.std(0, ddof=1) if len(results) > 1 else np.zeros(means.shape[1])
    return Level2Result(means=means, stds=np.stack([r.std for r in results]), spread=spread, level1=results,
                        free=results[0].free, global_mean=means.mean(0), global_running=running_means(means),
                        global_samples=running_means(_set_means(results)), stopped=stopped, global_tol=global_tol,
                        timings=timings)
