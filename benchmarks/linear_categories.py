"""The linear formulation study of seed 000 ch. 4 / ch. 6.1 on MRR-1: the four categories of Table 4.1,
position-only calibration (Figure 6.6a), orthogonality loss and divergence of the skew update, and
the PRY-difference branch cut. One process; the first call of each setting (compile) timed apart.

    PYTHONPATH=. python benchmarks/linear_categories.py [--out benchmarks/results/linear_categories]

Writes OUT.json (every history) and OUT.png (four panels).
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import first_and_median  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.fit.linear import CATEGORIES, linear_calibrate  # noqa: E402
from jaxcal.report import save_atomic, write_text_atomic  # noqa: E402

# seed 000 Table 6.6: "actual" tip pose of MRR-1 at the Table 6.1 joint motions
P_ACTUAL = np.array([0.42722476, 0.65018508, 0.25310769])
R_ACTUAL = np.array([[-1.8588651e-4, -9.9999914e-1, 1.2975389e-3],
                     [-9.9998926e-1, 1.7987616e-4, -4.6306960e-3],
                     [4.6304586e-3, -1.2983857e-3, -9.9998844e-1]])
FLOOR = 1e-17  # plotted in place of exact zeros on log axes
STYLES = [dict(marker="o", ls="-", ms=7), dict(marker="s", ls="--", ms=5),
          dict(marker="^", ls="-", ms=7), dict(marker="v", ls="--", ms=5)]


def _summary(r) -> dict:
    rmsoe = [None if np.isnan(v) else v for v in r.rmsoe.tolist()]  # NaN (no rotations measured) -> JSON null
    return {"converged": r.converged, "iterations": r.iterations, "rmspe": r.rmspe.tolist(), "rmsoe": rmsoe,
            "rmse": r.rmse.tolist(), "orthogonality": r.orthogonality.tolist(), "condition": r.condition.tolist(),
            "rank": r.rank.tolist()}


def study(n_poses: int = 8, seeds=(0, 1, 2, 3, 4)):
    rb = jc.robots.get("mrr1")
    home = np.asarray(rb.home)[None]
    out = {"single_pose_position": {}, "single_pose_full": {}, "many_poses": {}, "timing": {}}
    for axes in ("static", "moving"):
        for upd in ("pry", "skew"):
            fn = lambda: linear_calibrate(rb, home, None, P_ACTUAL[None], "position", update=upd, axes=axes, tol=1e-6)  # noqa: E731
            r, first, med = first_and_median(fn, repeat=5)
            out["single_pose_position"][f"{axes}/{upd}"] = _summary(r)
            out["timing"][f"single_pose_position/{axes}/{upd}"] = {"first_s": first, "median_s": med, "iterations": r.iterations}
    for cat in CATEGORIES:
        r = linear_calibrate(rb, home, R_ACTUAL[None], P_ACTUAL[None], "pose", category=cat, tol=1e-6, max_iter=20)
        out["single_pose_full"][str(cat)] = _summary(r)
    for seed in seeds:
        a_true = jc.perturb(rb, 0.003, seed=seed)
        Q = jc.random_configurations(rb, n_poses, seed=10 + seed)
        pose = jc.forward(rb, a_true, Q)
        R, p = np.asarray(pose.R), np.asarray(pose.p)
        runs = {f"position/{upd}": linear_calibrate(rb, Q, None, p, "position", update=upd, tol=1e-6) for upd in ("pry", "skew")}
        runs["position/seed-J/pry"] = linear_calibrate(rb, Q, None, p, "position", update="pry", axes="moving", tol=1e-6)
        for cat in CATEGORIES:
            runs[f"pose/cat{cat}"] = linear_calibrate(rb, Q, R, p, "pose", category=cat, tol=1e-6, max_iter=20)
        out["many_poses"][str(seed)] = {k: _summary(v) for k, v in runs.items()}
    a_true = jc.perturb(rb, 0.003, seed=0)
    Q = jc.random_configurations(rb, n_poses, seed=10)
    pose = jc.forward(rb, a_true, Q)
    fn = lambda: linear_calibrate(rb, Q, np.asarray(pose.R), np.asarray(pose.p), "pose", category=3, tol=1e-6)  # noqa: E731
    r, first, med = first_and_median(fn, repeat=5)
    out["timing"][f"many_poses_full/cat3/{n_poses}"] = {"first_s": first, "median_s": med, "iterations": r.iterations}
    return out


def _log(y):
    return np.maximum(np.asarray(y, float), FLOOR)


def plot(out, path):
    fig, ax = plt.subplots(2, 2, figsize=(13, 9.5))
    a = ax[0, 0]
    labels = {"static/pry": "J of increments, PRY update", "static/skew": "J of increments, skew update",
              "moving/pry": "seed J (eq 4.3b), PRY update", "moving/skew": "seed J (eq 4.3b), skew update"}
    for (k, r), st in zip(out["single_pose_position"].items(), STYLES):
        a.semilogy(_log(r["rmspe"]), label=labels[k], **st)
    a.semilogy([0, 4], [3.8e-3, 6.2e-7], "k*", ms=14, label="seed Fig. 6.6(a): 3.8e-3 -> 6.2e-7 m")
    a.axhline(1e-6, color="gray", ls=":", lw=1)
    a.set(title="(a) position-only, one pose (Table 6.6)", xlabel="iteration", ylabel="RMSPE (m)")
    a.legend(fontsize=8)
    a = ax[0, 1]
    names = {"1": "1: vect, skew", "2": "2: PRY diff, skew", "3": "3: vect, PRY", "4": "4: PRY diff, PRY"}
    for (k, r), st in zip(out["single_pose_full"].items(), STYLES):
        a.semilogy(_log(r["rmse"]), label=f"cat. {names[k]}" + ("" if r["converged"] else " (no conv.)"), **st)
    a.axhline(1e-6, color="gray", ls=":", lw=1)
    a.set(title="(b) full pose, one pose: Table 4.1 categories", xlabel="iteration", ylabel="RMSE (m, rad)")
    a.legend(fontsize=8)
    a = ax[1, 0]
    for (k, r), st in zip(out["single_pose_full"].items(), STYLES):
        a.semilogy(_log(r["orthogonality"]), label=f"cat. {names[k]}", **st)
    a.set(title="(c) orthogonality of R_s, full pose, one pose", xlabel="iteration", ylabel="max ||R_s^T R_s - I||_F")
    a.legend(fontsize=8)
    a = ax[1, 1]
    colors = {"position/pry": "C0", "position/skew": "C3", "position/seed-J/pry": "C2", "pose/cat3": "C1"}
    for seed, runs in out["many_poses"].items():
        for k, c in colors.items():
            a.semilogy(_log(runs[k]["rmspe"]), "-", color=c, alpha=0.7, label=k if seed == "0" else None)
    a.set_ylim(1e-12, 1e3)
    a.axhline(1e-6, color="gray", ls=":", lw=1)
    n_seeds = len(out["many_poses"])
    a.set(title=f"(d) 8 random poses, errors N(0, 0.003), {n_seeds} draws", xlabel="iteration", ylabel="RMSPE (m)")
    a.legend(fontsize=8)
    fig.suptitle("Linear formulation on MRR-1 (seed 000 ch. 4, 6.1)")
    fig.tight_layout()
    return save_atomic(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results/linear_categories")
    args = ap.parse_args(argv)
    out = study()
    write_text_atomic(args.out + ".json", json.dumps(out, indent=1))
    plot(out, args.out + ".png")
    for k, r in out["single_pose_position"].items():
        print(f"position one pose {k:<12} iterations {r['iterations']}  RMSPE {' '.join(f'{v:.2e}' for v in r['rmspe'])}")
    for k, r in out["single_pose_full"].items():
        print(f"full pose one pose cat {k}  converged {r['converged']!s:<5} it {r['iterations']:>2}  "
              f"RMSE[0] {r['rmse'][0]:.2e} RMSE[-1] {r['rmse'][-1]:.2e}  max orth {max(r['orthogonality']):.1e}")
    keys = next(iter(out["many_poses"].values())).keys()
    for k in keys:
        conv = [runs[k]["converged"] for runs in out["many_poses"].values()]
        its = [runs[k]["iterations"] for runs in out["many_poses"].values() if runs[k]["converged"]]
        print(f"8 poses {k:<22} converged {sum(conv)}/{len(conv)}  iterations {its}")
    for k, t in out["timing"].items():
        print(f"time {k:<40} first (compile) {t['first_s']:.2f} s  median {t['median_s'] * 1e3:.1f} ms  ({t['iterations']} it)")


if __name__ == "__main__":
    main()
