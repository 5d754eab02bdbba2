"""The seed's GA figures on MRR-1 (seed 000 Figures 6.9-6.12), computed by the engine and plotted.

    PYTHONPATH=. python benchmarks/ga_figures.py [--out benchmarks/results]

Data: MRR-1, 8 random configurations, noise-free pose readings of a robot whose 18 PRY parameters
are off by uniform +-4 mm / mrad (as tests/test_ga.py). Writes ga_fig6_9.png (best and mean fitness
per generation, 50 x 250), ga_fig6_10.png (population/generation study: median over 8 runs of the
best fitness), ga_fig6_11.png (level-1 Monte Carlo: running means over 50 runs and the eq 5.7
change for the parameters and for the predicted tip positions), ga_fig6_12.png (level 2, loop 3
of Figure 5.2: level 1 on single random configurations, 8 per vmapped round, until the running
global mean of eq 5.10 settles) and ga_figures.json with the numbers.
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
from jaxcal.ga import montecarlo as mc  # noqa: E402
from jaxcal.report.plots import (  # noqa: E402
    plot_ga_history,
    plot_ga_population_study,
    plot_monte_carlo_level1,
    plot_monte_carlo_level2,
    write_text_atomic,
)

LEVEL2_MAX_SETS = 32  # loop 3: rounds of 8 single configurations until eq 5.10's mean settles, at most 4 rounds
STUDY = ((50, 250), (100, 1000), (150, 1000), (200, 1000), (200, 1500))  # seed Figure 6.10 settings (+ the 50 x 250 run)


def _change(samples):
    return np.max(np.abs(np.diff(mc.running_means(samples), axis=0)), axis=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    rb = jc.robots.get("mrr1")
    a_true = rb.nominal + np.random.default_rng(3).uniform(-0.004, 0.004, rb.n_params)
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 8, seed=1), "pose")
    out, t0 = {"load_average_at_start": os.getloadavg()}, time.perf_counter()

    ga = jc.ga.calibrate(rb, data, population=50, generations=250, seed=0)
    out["fig6_9"] = {"best_first": float(ga.best[0]), "best_final": float(ga.best[-1]), "mean_final": float(ga.mean[-1]),
                     "seed_reports": "4.5e-3 -> 9.8075e-6"}
    plot_ga_history(ga.best, ga.mean, os.path.join(args.out, "ga_fig6_9.png"),
                    title="MRR-1, population 50 x 250 generations (seed Figure 6.9)")

    curves, study = {}, {}
    for pop, gens in STUDY:
        r = jc.ga.calibrate(rb, data, population=pop, generations=gens, seed=1, runs=8, chunk=50)
        curves[f"population {pop}, {gens} generations"] = np.median(r.runs_best, axis=0)
        study[f"{pop}x{gens}"] = {"median_final_best": float(np.median(r.runs_fitness)), "best_final": float(r.runs_fitness.min()),
                                  "run_s_8_runs": r.timings["run_s"]}
    out["fig6_10"] = study
    plot_ga_population_study(curves, os.path.join(args.out, "ga_fig6_10.png"),
                             title="MRR-1: population and generations (seed Figure 6.10), median of 8 runs")

    l1 = mc.level1(rb, data, tol=0.0, batch=10, max_runs=50, stop_on="tip", population=50, generations=250)
    ch_p, ch_t = _change(l1.dg), _change(l1.samples)
    tols = {"parameters dg (rad, m)": 1e-5, "tip positions (m)": 1e-6}
    stop_p, stop_t = mc.stopping_index(l1.dg, 1e-5), mc.stopping_index(l1.samples, 1e-6)
    out["fig6_11"] = {"runs": l1.runs, "stop_parameters_tol_1e-5": stop_p, "stop_tip_tol_1e-6_m": stop_t,
                      "change_parameters_last": float(ch_p[-1]), "change_tip_last_m": float(ch_t[-1])}
    plot_monte_carlo_level1(l1.running_mean, dict(zip(tols, (ch_p, ch_t))), tols, os.path.join(args.out, "ga_fig6_11.png"),
                            title=f"MRR-1 level 1, 50 GA runs (seed Figure 6.11): eq 5.7 met after {stop_t} runs on tip "
                                  f"positions, {'never' if stop_p is None else stop_p} on parameters")

    check_q = mc.random_configurations(rb, 10, seed=12345)
    true_tips = np.asarray(jc.forward(rb, jnp.asarray(a_true), jnp.asarray(check_q)).p).reshape(-1)
    runs = {}
    for n_conf in (1, 8):  # the seed's single configuration per level-1 loop, and sets of 8 configurations
        l2 = mc.level2(rb, jnp.asarray(a_true), "pose", m=8, max_sets=LEVEL2_MAX_SETS, n_configurations=n_conf, tol=1e-6,
                       global_tol=1e-6, batch=10, max_runs=30, stop_on="tip", check_q=check_q, population=50,
                       generations=250)
        tip_err = [float(np.max(np.abs(r.samples.mean(0) - true_tips))) for r in l2.level1]
        stable = l2.stable(1e-5)
        out[f"fig6_12_{n_conf}_configurations_per_set"] = {
            "sets": l2.sets, "stopped": l2.stopped, "runs_per_set": [r.runs for r in l2.level1],
            "level1_stopped": int(sum(r.stopped for r in l2.level1)), "tip_error_m_per_set": tip_err,
            "global_tip_error_m": float(np.max(np.abs(l2.global_samples[-1] - true_tips))),
            "global_change_last": float(np.max(np.abs(l2.global_running[-1] - l2.global_running[-2]))),
            "stable_parameters_1e-5": int(stable.sum()), "unstable": [n for n, s in zip(l2.free, stable) if not s],
            "spread_of_means_max": float(l2.spread.max()), "spread_of_means_min": float(l2.spread.min()),
            "timings": l2.timings}
        runs[n_conf] = (l2, tip_err, stable)
    l2, tip_err, stable = runs[1]
    plot_monte_carlo_level2(l2.global_running, l2.free, tip_err, os.path.join(args.out, "ga_fig6_12.png"), stable=stable,
                            title=f"MRR-1 level 2 (seed Figure 6.12, eq 5.10): {l2.sets} random configurations, "
                                  f"{int(stable.sum())} of {len(stable)} parameters stable to 1e-5")
    out["wall_s"], out["load_average_at_end"] = time.perf_counter() - t0, os.getloadavg()
    write_text_atomic(os.path.join(args.out, "ga_figures.json"), json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
