"""Identifiability per calibration method (seed 001 §3, App. III), optimal configurations, and GECARO's
iterated linearised least squares vs Levenberg-Marquardt. One process; first calls (compile) apart.

    PYTHONPATH=. python benchmarks/identifiability.py [--out benchmarks/results/identifiability.json]

1. Stanford (nine methods) and MRR-1 (position, location): identifiable count, cond(W_b), the
   observability indices and the time of `jc.identifiable` (first call, then median of repeats).
2. Stanford + position: 15 configurations chosen by `select_configurations` vs random 15-subsets.
3. GECARO (dx = -W_b^+ r, seed 001 eq 9-10) vs LM (jaxcal.fit.lm) on the same noise-free Stanford
   position data: iterations, final RMS, parameter error, time, and success over error scales.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from _common import first_and_median  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.fit.design import random_design_conditions, select_configurations  # noqa: E402
from jaxcal.fit.identifiable import calibrate  # noqa: E402
from jaxcal.fit.methods import METHODS, generate_points  # noqa: E402
from jaxcal.report import write_text_atomic  # noqa: E402

TABLE2 = dict(zip(METHODS, (31, 34, 24, 21, 27, 24, 26, 24, 25)))


def identifiability_table(n_configs=40):
    rows = []
    for robot_name, methods in (("stanford", METHODS), ("mrr1", ("position", "location"))):
        rb = jc.robots.get(robot_name)
        for m in methods:
            r, first, med = first_and_median(lambda: jc.identifiable(rb, m, n_configs=n_configs, seed=0))
            paper = TABLE2.get(m) if robot_name == "stanford" else None
            rows.append({"robot": robot_name, "method": m, "count": r.count, "paper": paper,
                         "n_params": rb.n_params, "condition": r.condition, **r.indices, "first_s": first, "median_s": med})
    return rows


def design_study():
    rb = jc.robots.get("stanford")
    pool = jc.random_configurations(rb, 400, seed=0)
    out = {}
    for index in ("condition", "menq_borm", "min_singular", "noise_amplification"):
        d, first, med = first_and_median(lambda: select_configurations(rb, "position", n=15, pool=pool, index=index), repeat=1)
        out[index] = {"condition": d.condition, **{f"chosen_{k}": v for k, v in d.indices.items()},
                      "exchanges": d.exchanges, "first_s": first, "median_s": med}
    rand = random_design_conditions(rb, "position", n=15, pool=pool, draws=50, seed=0)
    out["random_15"] = {"median_condition": float(np.median(rand)), "best_condition": float(rand.min()),
                        "worst_condition": float(rand.max()), "draws": len(rand)}
    return out


def gecaro_vs_lm(scales=(1e-3, 1e-2, 5e-2, 1e-1, 2e-1, 3e-1), seeds=range(5), n_points=40):
    """True robot: base-set entries of nominal perturbed uniformly by +-scale (lengths in m, angles in rad,
    gains x4); noise-free position points of the true robot; both solvers start from nominal."""
    rb = jc.robots.get("stanford")
    ident = jc.identifiable(rb, "position", n_configs=40, seed=1)
    base = np.array([rb.index(n) for n in ident.names])
    gain = np.array([u == "gain" for u in rb.units])
    out = []
    for scale in scales:
        for seed in seeds:
            rng = np.random.default_rng(seed)
            a_true = rb.nominal_np.copy()
            a_true[base] += (scale * np.where(gain, 4.0, 1.0))[base] * rng.uniform(-1, 1, len(base))
            pts = generate_points(rb, "position", n_points, seed=100 + seed, a=a_true)
            for solver in ("gecaro", "lm"):
                cal, first, med = first_and_median(lambda: calibrate(rb, pts, solver=solver, max_iter=50), repeat=2)
                err = float(np.max(np.abs(cal.a - a_true)))
                out.append({"scale": scale, "seed": seed, "solver": solver, "iterations": cal.iterations,
                            "rms_before": float(cal.rms[0]), "rms_after": float(cal.rms[-1]), "param_error": err,
                            "success": bool(err < 1e-8), "first_s": first, "median_s": med})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results/identifiability.json")
    args = ap.parse_args(argv)
    out = {"identifiable": identifiability_table(), "design": design_study(), "gecaro_vs_lm": gecaro_vs_lm()}
    write_text_atomic(args.out, json.dumps(out, indent=1))
    print(f"{'robot':<9}{'method':<16}{'count':>6}{'paper':>6}{'cond(W_b)':>11}{'menq_borm':>11}{'min_sv':>10}{'noise_amp':>11}"
          f"{'first s':>9}{'median s':>10}")
    for r in out["identifiable"]:
        print(f"{r['robot']:<9}{r['method']:<16}{r['count']:>6}{r['paper'] or '':>6}{r['condition']:>11.3g}{r['menq_borm']:>11.3g}"
              f"{r['min_singular']:>10.3g}{r['noise_amplification']:>11.3g}{r['first_s']:>9.2f}{r['median_s']:>10.3f}")
    d = out["design"]
    print(f"\n15 random of 400 (50 draws): cond median {d['random_15']['median_condition']:.1f}, "
          f"best {d['random_15']['best_condition']:.1f}, worst {d['random_15']['worst_condition']:.1f}")
    for k in ("condition", "menq_borm", "min_singular", "noise_amplification"):
        print(f"chosen by {k:<20} cond {d[k]['condition']:.1f}  exchanges {d[k]['exchanges']:>3}  "
              f"first {d[k]['first_s']:.2f} s  again {d[k]['median_s']:.2f} s")
    print(f"\n{'scale':>7}{'solver':>8}{'success':>9}{'iter median':>12}{'iter max':>9}{'rms after max':>15}{'time median s':>14}")
    rows = out["gecaro_vs_lm"]
    for scale in sorted({r["scale"] for r in rows}):
        for solver in ("gecaro", "lm"):
            sel = [r for r in rows if r["scale"] == scale and r["solver"] == solver]
            print(f"{scale:>7g}{solver:>8}{sum(r['success'] for r in sel):>5}/{len(sel):<3}"
                  f"{statistics.median(r['iterations'] for r in sel):>12g}{max(r['iterations'] for r in sel):>9}"
                  f"{max(r['rms_after'] for r in sel):>15.2e}{statistics.median(r['median_s'] for r in sel):>14.3f}")


if __name__ == "__main__":
    main()
