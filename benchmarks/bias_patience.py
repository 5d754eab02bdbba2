"""Where should the k-fold bias path stop? (`jaxcal.fit.bias.PATIENCE`, `RISE`; issue 18: the Delta's call.)

For each simulated case whose default `identify` chooses its bias by k-fold held-out error, the whole path is run
(every stage, whatever the scores), and the stopping rules are replayed on its pooled held-out scores
(`fit.bias.path_ends`: stop once `patience` stages past the least exceed it by more than the share `rise`, or more
than `patience` stages lie past it). A rule is as good as running the whole path where it picks the same stage;
where two picks differ, both schedules are fitted and their model's RMS tool-position (or reading) error on 200 new
noise-free settings is printed.

Cases: the Delta (seed 004 Table 4.6) from 60 and 125 positions at 0.01, 0.03 and 0.1 mm noise, and by theodolite
(0.013 mrad, instrument and marker known), the Kiwibot from 60 positions (0.02, 0.1 mm), the TALOS arm, UR10 and
Stanford arm from 20 positions with the tracker 4 m away and turned 150 degrees (0.05 mm; `defaults_cv.far_frame`),
seeds --seed .. --seed + 3 (fewer for the small groups), and the Delta of `make bench` (125 positions, 0.01 mm).

    PYTHONPATH=. python benchmarks/bias_patience.py [--seed 1] [--out benchmarks/results/bias_patience_1.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import _common  # noqa: F401  (OPENBLAS_NUM_THREADS before numpy)
import numpy as np
from defaults_cv import far_frame

import jaxcal as jc
from jaxcal.fit import bias
from jaxcal.report import write_text_atomic

RULES = [(1, 0.0), (1, 1e-3), (1, 2e-3), (1, 5e-3), (1, 1e-2), (2, 0.0)]


def stop_stage(scores, patience: int, rise: float) -> tuple[int, int]:
    """(chosen stage, stages run) under `fit.bias.path_ends`' rule with these patience and rise."""
    for k in range(len(scores)):
        if bias.path_ends(scores[:k + 1], patience, rise):
            return bias.least_stage(scores[:k + 1]), k + 1
    return bias.least_stage(scores), len(scores)


def cases(seed: int):
    """(label, robot name, samples, seed, device kind, noise, options) of each case."""
    yield "make bench's Delta", "delta", 125, None, "position", {"position": 1e-5}, {}
    for n in (125, 60):
        for s in range(seed, seed + 4):
            for noise in (1e-5, 3e-5, 1e-4):
                yield f"Delta {n} positions, seed {s}, {noise * 1e3:g} mm", "delta", n, s, "position", {"position": noise}, {}
    for s in range(seed, seed + 3):
        for noise in (2e-5, 1e-4):
            yield f"Kiwibot 60 positions, seed {s}, {noise * 1e3:g} mm", "kiwibot", 60, s, "position", {"position": noise}, {}
    for s in range(seed, seed + 3):
        yield f"Delta 125 theodolite readings, seed {s}", "delta", 125, s, "theodolite", {"orientation": 1.3e-5}, \
            {"known": ("dev", "tool")}
    for name in ("talos_left_arm", "ur10", "stanford"):
        for s in range(seed - 1, seed + 2):
            yield f"{name} 20 positions, far tracker, seed {s}", name, 20, s, "position", {"position": 5e-5}, {"far": True}


def simulate(name: str, n: int, seed, kind: str, noise: dict, far: bool):
    rb = jc.robots.get(name)
    dev = jc.make_device(kind)
    if seed is None:  # benchmarks/table.py's Delta
        a_true, q, seed = jc.perturb(rb, 1e-3, seed=1), jc.random_configurations(rb, 125, seed=2), 3
    else:
        a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3} if far else 1e-3, seed=seed)
        q = jc.random_configurations(rb, n, seed=seed + 10)
    extra = {"device_params": far_frame(dev.n_params, seed)} if far else {}
    data = jc.simulate(rb, a_true, q, dev, noise=noise, seed=seed, **extra)
    test = jc.simulate(rb, a_true, jc.random_configurations(rb, 200, seed=seed + 100), dev, noise=0.0, seed=seed, **extra)
    return rb, data, test


def run_case(label, name, n, seed, kind, noise, options) -> dict | None:
    rb, data, test = simulate(name, n, seed, kind, noise, options.get("far", False))
    fit_kw = {"known": options["known"]} if "known" in options else {}
    fit_kw.update({"sigma_position": noise["position"]} if "position" in noise else {"sigma_orientation": noise["orientation"]})
    scores = []
    whole_path = bias.heldout_scores

    def every_stage(*a, **k):
        out = whole_path(*a, **{**k, "patience": len(bias.BIAS_PATH) + 1})
        scores.append(out[0])
        return out

    bias.heldout_scores = every_stage
    try:
        t = time.perf_counter()
        fit = jc.identify(rb, data, **fit_kw)
        wall = time.perf_counter() - t
    finally:
        bias.heldout_scores = whole_path
    if not scores:
        return None
    every_free = bool(fit.info.get("bias_every_free"))
    path = bias.PRIOR_PATH if every_free else bias.BIAS_PATH
    picks = {f"patience {p}, rise {r:g}": stop_stage(scores[0], p, r) for p, r in RULES}
    whole = bias.least_stage(scores[0])
    rms = {}
    for stage in sorted({whole, *(c for c, _ in picks.values())}):
        refit = jc.identify(rb, data, bias=[float(m) for m in path[:stage + 1]], base=not every_free, **fit_kw)
        rms[stage] = refit.rms_on(test)
    return {"case": label, "scores": np.asarray(scores[0]).tolist(), "whole_path": whole, "picks": picks,
            "rms_new_settings": rms, "identify_s": wall}


def summary(rows) -> list[str]:
    lines = [f"{len(rows)} cases with a k-fold bias path"]
    for key in (f"patience {p}, rise {r:g}" for p, r in RULES):
        ref = "patience 2, rise 0"
        differ = [r["case"] for r in rows if r["picks"][key][0] != r["picks"][ref][0]]
        stages = sum(r["picks"][key][1] for r in rows)
        lines.append(f"{key}: stages run {stages}; picks other than patience 2's: {len(differ)} {differ}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = args.out or os.path.join(os.path.dirname(__file__), "results", f"bias_patience_{args.seed}.json")
    rows = []
    for case in cases(args.seed):
        row = run_case(*case)
        if row is None:
            print(f"{case[0]}: no k-fold bias path", flush=True)
            continue
        rows.append(row)
        rel = ", ".join(f"{v / np.nanmin(row['scores']):.4f}" for v in row["scores"])
        rms = ", ".join(f"stage {k}: {v:.4g}" for k, v in row["rms_new_settings"].items())
        print(f"{row['case']}: scores / least [{rel}]; whole path {row['whole_path']}; "
              f"patience 1 rise 0: {row['picks']['patience 1, rise 0'][0]}, patience 1 rise 5e-3: "
              f"{row['picks']['patience 1, rise 0.005'][0]}, patience 2: {row['picks']['patience 2, rise 0'][0]}; "
              f"RMS on new settings {rms}", flush=True)
    print("\n".join(summary(rows)))
    write_text_atomic(out, json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
