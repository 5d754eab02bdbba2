"""Does the default win held out? `identify`'s defaults against a nested cross-validation (issue 15 item 3).

For each dataset: 5-fold cross-validation of `identify(robot, data)` with its defaults (what `jaxcal calibrate`
runs), and a nested cross-validation (`jaxcal.fit.cv.nested_cross_validate`) that chooses per outer fold, by a
4-fold inner cross-validation on the training samples only, among candidates fixed before any fit: the default,
every parameter with the bias term at mu in MU (seed 004 eq 3.12), and the default with outliers excluded.
Both use the same outer folds, so their per-sample held-out errors pair up; the verdict compares the mean
squared held-out error: "default" (lower), "nested" (lower by more than 2 paired standard errors) or "tie".

Datasets: the three real ones shipped with jaxcal (FIGAROH's TALOS, UR10, TIAGo; a-priori weights of
`jaxcal.realdata`) and simulated arms with ordinary errors (1 mm lengths, 2 mrad angles, 0.1 % gains;
20 and 60 positions; tracker 4 m away and rotated 150 degrees; 0.05 mm noise per axis; marker 5 cm off).

    PYTHONPATH=. python benchmarks/defaults_cv.py [--only talos,ur10] [--markdown]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import _common  # noqa: F401  (OPENBLAS_NUM_THREADS before numpy)
import numpy as np

import jaxcal as jc
from jaxcal.fit.cv import cross_validate, nested_cross_validate

RESULTS = os.path.join(os.path.dirname(__file__), "results", "defaults_cv.json")
MU = (1e-2, 1e-1, 1.0, 10.0)
NOISE = 5e-5
CANDIDATES = {"default": {}, **{f"prior mu={mu:g}": {"base": False, "bias": [mu]} for mu in MU},
              "outliers excluded": {"outliers": "exclude"}}


def far_frame(n_params: int, seed: int) -> np.ndarray:
    """Position-device parameters: the tracker 4 m away, turned 150 degrees about a random axis; 5 cm marker."""
    rng = np.random.default_rng(seed)
    d = np.zeros(n_params)
    d[:3] = 4.0 * rng.normal(size=3) / np.linalg.norm(rng.normal(size=3))
    d[:3] *= 4.0 / np.linalg.norm(d[:3])
    axis = rng.normal(size=3)
    d[3:6] = np.deg2rad(150.0) * axis / np.linalg.norm(axis)
    d[6:9] = [0.02, -0.03, 0.04]
    return d


def simulated_case(robot_name: str, n: int, seed: int = 0):
    rb = jc.robots.get(robot_name)
    a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=seed)
    dev = jc.make_device("position")
    q = jc.random_configurations(rb, n, seed=seed + 1)
    data = jc.simulate(rb, a_true, q, dev, noise={"position": NOISE}, device_params=far_frame(dev.n_params, seed), seed=seed)
    return rb, data, {"sigma_position": NOISE}


def real_case(name: str):
    real = jc.realdata.load(name)
    return real.robot, real.data, {"sigma_orientation": jc.realdata.SIGMA_ORIENTATION[name]}


CASES = {
    "talos": lambda: real_case("talos"),
    "ur10": lambda: real_case("ur10"),
    "tiago": lambda: real_case("tiago"),
    **{f"sim {r} {n}": (lambda r=r, n=n: simulated_case(r, n)) for r in ("ur10", "stanford", "talos_left_arm")
       for n in (20, 60)},
}


def paired_verdict(default_errors, nested_errors) -> tuple[str, float]:
    """("default" | "nested" | "tie", z) from the per-sample squared held-out errors, paired by sample."""
    d = np.asarray(default_errors) ** 2 - np.asarray(nested_errors) ** 2
    se = np.std(d, ddof=1) / np.sqrt(len(d))
    z = float(np.mean(d) / se) if se > 0 else 0.0
    if np.mean(d) <= 0:
        return "default", z
    return ("nested" if z > 2.0 else "tie"), z


def run_case(label: str) -> dict:
    robot, data, common = CASES[label]()
    t0 = time.perf_counter()
    plain = cross_validate(robot, data, folds=5, seed=0, **common)
    nested = nested_cross_validate(robot, data, CANDIDATES, folds=5, inner_folds=4, seed=0, **common)
    verdict, z = paired_verdict(plain.heldout_errors, nested.heldout_errors)
    return {"dataset": label, "samples": len(data), "device": data.device.kind,
            "default_heldout": plain.heldout_after, "frames_only_heldout": plain.heldout_before,
            "nested_heldout": nested.heldout, "verdict": verdict, "z": z,
            "default_converged": sum(r["converged"] for r in plain.per_fold),
            "nested_converged": sum(nested.converged), "folds": 5, "chosen": list(nested.chosen),
            "wall_s": time.perf_counter() - t0}


def markdown(rows) -> str:
    lines = ["| data | samples | frames only | default held-out | nested held-out | verdict (z) | default converged | "
             "nested chose (per fold) | wall s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['dataset']} | {r['samples']} | {r['frames_only_heldout']:.4g} | **{r['default_heldout']:.4g}** | "
                     f"{r['nested_heldout']:.4g} | {r['verdict']} ({r['z']:+.2f}) | {r['default_converged']}/{r['folds']} | "
                     f"{', '.join(r['chosen'])} | {r['wall_s']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", help="comma-separated dataset labels (default: all)")
    ap.add_argument("--markdown", action="store_true", help="print the table of the saved results")
    args = ap.parse_args(argv)
    saved = json.load(open(RESULTS)) if os.path.exists(RESULTS) else {}
    if args.markdown:
        print(markdown([saved[k] for k in CASES if k in saved]))
        return 0
    for label in (args.only.split(",") if args.only else CASES):
        row = run_case(label)
        saved[label] = row
        print(json.dumps(row), flush=True)
        tmp = RESULTS + ".tmp"
        with open(tmp, "w") as f:
            json.dump(saved, f, indent=1)
        os.replace(tmp, RESULTS)
    print(markdown([saved[k] for k in CASES if k in saved]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
