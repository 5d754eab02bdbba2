"""GA throughput on MRR-1 (seed 000 ch. 5-6), compile time apart, medians of repeats, one process.

    PYTHONPATH=. python benchmarks/ga.py [--repeats 3] [--out benchmarks/results/ga.json]

Reports, for 8 measured configurations (pose data, seed eq 5.3-5.4 fitness):
- generations/s and fitness evaluations/s for populations 50, 200, 1000 (250 generations), per
  wall second and per CPU second of this process (the shared machine's load inflates wall time);
- the same GA with the fitness evaluated per individual and vmapped (the path of robots that
  `jaxcal.ga.batched` does not model) against the population-wide fitness, in this process (ratio);
- 50 Monte Carlo runs (population 50 x 250 generations) vmapped in one call vs 50 sequential
  calls of the same compiled single-run function (ratio);
- wall time of the seed's experiment (50 individuals x 250 generations), against the seed's
  "a few minutes" in MATLAB (seed 000 §6.2).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.ga import batched, core  # noqa: E402
from jaxcal.ga.fitness import pose_fitness  # noqa: E402
from jaxcal.ga.runner import run  # noqa: E402
from jaxcal.report import write_text_atomic  # noqa: E402


def _data():
    rb = jc.robots.get("mrr1")
    a_true = rb.nominal + np.random.default_rng(3).uniform(-0.004, 0.004, rb.n_params)
    return rb, jc.simulate(rb, a_true, jc.random_configurations(rb, 8, seed=1), "pose")


def _with_cpu_time(fn):
    """fn() (a GAResult) with the process CPU time of the call added to its timings: on this shared
    machine wall time includes waiting for a core; XLA ran the GA on one thread."""
    t = time.process_time()
    res = fn()
    res.timings["cpu_s"] = time.process_time() - t
    return res


def _timed(fn, repeats):
    first = fn()  # compiles (AOT cache in the runner) and warms up
    runs = [fn() for _ in range(repeats)]
    return first, runs


def fitness_paths(rb, data, population, generations, repeats):
    """Median run time of one GA chunk with the per-individual vmapped fitness and with the
    population-wide fitness (same operators, same data, this process), compile time apart."""
    dev = data.device
    payload = dict(q=jnp.asarray(data.q), y=jnp.asarray(data.y), a0=jnp.concatenate([rb.nominal, dev.nominal]))
    free_idx = tuple(int(i) for i in np.flatnonzero(rb.free_mask))
    idx = jnp.asarray(free_idx)
    lb, ub = -0.005 * jnp.ones(len(free_idx)), 0.005 * jnp.ones(len(free_idx))
    opts = core.GAOptions(population=population, generations=generations)
    keys = jax.random.split(jax.random.PRNGKey(0), 1)

    def one(dg, data):
        return pose_fitness(rb, dev, data["a0"].at[idx].add(dg), data["q"], data["y"])

    def whole(pops, data):
        return batched.population_fitness(rb, dev, data["a0"], free_idx, pops, data["q"], data["y"])

    out = {}
    for name, fn, is_batched in (("vmapped", one, False), ("population", whole, True)):
        state = core.make_init_fn(fn, opts, batched=is_batched)[1](keys, payload, lb, ub)
        chunk = core.make_chunk_fn(fn, opts, generations, batched=is_batched)
        t = time.perf_counter()
        jax.block_until_ready(chunk(state, payload, lb, ub))
        compile_s = time.perf_counter() - t
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(chunk(state, payload, lb, ub))
            times.append(time.perf_counter() - t)
        run_s = statistics.median(times)
        out[name] = {"compile_and_first_run_s": compile_s, "run_s_median": run_s,
                     "evaluations_per_s": population * generations / run_s}
    out["speedup"] = out["vmapped"]["run_s_median"] / out["population"]["run_s_median"]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--generations", type=int, default=250)
    ap.add_argument("--out", default="benchmarks/results/ga.json")
    args = ap.parse_args(argv)
    rb, data = _data()
    G = args.generations
    out = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "configurations": 8,
           "load_average_at_start": os.getloadavg(),
           "generations": G, "populations": {}}

    for pop in (50, 200, 1000):
        first, runs = _timed(lambda: _with_cpu_time(lambda: run(rb, data, population=pop, generations=G, seed=0)),
                             args.repeats)
        run_s = statistics.median(r.timings["run_s"] for r in runs)
        cpu_s = statistics.median(r.timings["cpu_s"] for r in runs)
        evals = runs[0].timings["evaluations"]
        out["populations"][pop] = {"compile_s": first.timings["compile_s"], "run_s_median": run_s,
                                   "generations_per_s": G / run_s, "evaluations_per_s": evals / run_s,
                                   "cpu_s_median": cpu_s, "evaluations_per_cpu_s": evals / cpu_s,
                                   "final_best": runs[0].fitness}
        print(f"population {pop:5d}: compile {first.timings['compile_s']:.2f} s, run {run_s:.3f} s, "
              f"{G / run_s:9.0f} generations/s, {evals / run_s:.3e} evaluations/s (x8 configurations), "
              f"{evals / cpu_s:.3e} per CPU second")

    out["fitness_paths"] = {}
    for pop in (50, 1000):
        r = fitness_paths(rb, data, pop, G, max(args.repeats, 5))
        out["fitness_paths"][pop] = r
        print(f"population {pop:5d}: per-individual vmapped fitness {r['vmapped']['evaluations_per_s']:.3e}/s, "
              f"population-wide {r['population']['evaluations_per_s']:.3e}/s, ratio {r['speedup']:.1f}x")

    n_runs = 50
    first_v, vm = _timed(lambda: run(rb, data, population=50, generations=G, seed=0, runs=n_runs), args.repeats)
    vm_s = statistics.median(r.timings["run_s"] for r in vm)

    def sequential():
        t = time.perf_counter()
        for k in range(n_runs):
            run(rb, data, population=50, generations=G, seed=k)
        return time.perf_counter() - t

    sequential()  # warm (compiled single-run function already cached)
    seq_s = statistics.median(sequential() for _ in range(args.repeats))
    out["monte_carlo_50"] = {"vmapped_run_s": vm_s, "vmapped_compile_s": first_v.timings["compile_s"],
                             "sequential_s": seq_s, "speedup": seq_s / vm_s,
                             "vmapped_evaluations_per_s": vm[0].timings["evaluations"] / vm_s}
    print(f"50 Monte Carlo runs: vmapped {vm_s:.3f} s ({vm[0].timings['evaluations'] / vm_s:.3e} evaluations/s), "
          f"sequential {seq_s:.3f} s, ratio {seq_s / vm_s:.1f}x")

    seed_exp = out["populations"][50]
    out["seed_experiment_50x250_s"] = seed_exp["run_s_median"] * 250 / G
    print(f"seed experiment 50 x 250: {out['seed_experiment_50x250_s']:.3f} s run + {seed_exp['compile_s']:.2f} s compile "
          f"(seed: 'a few minutes' in MATLAB)")
    out["load_average_at_end"] = os.getloadavg()
    write_text_atomic(args.out, json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
