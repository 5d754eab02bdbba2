"""GA vs LM on MRR-1 (the seed's future-work question, seed 000 §8.3): accuracy, robustness from
100 random starts, time. One process; compile time apart.

    PYTHONPATH=. python benchmarks/ga_vs_lm.py [--starts 100] [--out benchmarks/results/ga_vs_lm.json]

Data: 8 random configurations, noise-free pose readings, known device frame/tool, true errors
uniform in +-4 mm / mrad. "Global minimum" = pose fitness (eq 5.3-5.4, summed over 8 poses) below
1e-4 (the nominal robot has 8.5e-2). LM starts: nominal + uniform +-5 mm / mrad (the GA's bound
box); GA runs: population 50 x 250 generations, uniform initial population, vmapped.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.ga.fitness import pose_fitness  # noqa: E402
from jaxcal.ga.runner import run  # noqa: E402
from jaxcal.report import write_text_atomic  # noqa: E402

THRESHOLD = 1e-4


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=100)
    ap.add_argument("--out", default="benchmarks/results/ga_vs_lm.json")
    args = ap.parse_args(argv)
    rb = jc.robots.get("mrr1")
    a_true = rb.nominal + np.random.default_rng(3).uniform(-0.004, 0.004, rb.n_params)
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 8, seed=1), "pose")
    dev, q, y = data.device, jnp.asarray(data.q), jnp.asarray(data.y)
    fit_of = lambda a: float(pose_fitness(rb, dev, jnp.concatenate([jnp.asarray(a), dev.nominal]), q, y))  # noqa: E731
    qt = jc.random_configurations(rb, 200, seed=9)
    held = lambda a: float(jnp.max(jnp.linalg.norm(jc.forward(rb, a, qt).p - jc.forward(rb, jnp.asarray(a_true), qt).p, axis=-1)))  # noqa: E731

    rng = np.random.default_rng(7)
    lm_fit, lm_run, lm_compile = [], [], 0.0
    for k in range(args.starts):
        a0 = rb.nominal + rng.uniform(-0.005, 0.005, rb.n_params)
        r = jc.identify(rb, data, known=("dev", "tool"), a0=a0)
        lm_fit.append(fit_of(r.a))
        lm_run.append(r.timings["run_s"])
        lm_compile = max(lm_compile, r.timings["compile_s"])
        if k == 0:
            lm_held = held(r.a)
    ga = run(rb, data, population=50, generations=250, seed=0, runs=args.starts)
    ga_fit = ga.runs_fitness
    nr = rb.n_params
    ga_best_a = jnp.asarray(rb.nominal).at[:].add(jnp.asarray(ga.runs_dg[int(np.argmin(ga_fit))])[:nr])
    out = {
        "nominal_fitness": fit_of(rb.nominal), "threshold": THRESHOLD,
        "lm": {"fraction_global": float(np.mean(np.array(lm_fit) < THRESHOLD)), "median_fitness": float(np.median(lm_fit)),
               "median_run_s": float(np.median(lm_run)), "compile_s": lm_compile, "heldout_max_mm": lm_held * 1e3},
        "ga": {"fraction_global": float(np.mean(ga_fit < THRESHOLD)), "median_fitness": float(np.median(ga_fit)),
               "best_fitness": float(ga_fit.min()), "run_s_all_runs_vmapped": ga.timings["run_s"],
               "run_s_per_run": ga.timings["run_s"] / args.starts, "compile_s": ga.timings["compile_s"],
               "heldout_max_mm_best_run": held(ga_best_a) * 1e3},
    }
    print(json.dumps(out, indent=2))
    write_text_atomic(args.out, json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
