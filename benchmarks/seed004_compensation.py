"""Seed 004 compensation ("implementation") studies not reproduced elsewhere (issue 16 item 6).

1. Kiwibot orientation compensation with the strut-length bias (§4.3, Figs 4.23-4.30): true robot =
   the thesis' perturbed model (Table 4.5); targets = the nominal nacelle pose at 160 hemisphere
   settings (`kiwibot.hemisphere_grid`, 0.7 m strut); the calibrated models are the thesis' own
   (perturbed + Table 4.5's identified - perturbed columns) and ours (`jc.identify` on simulation 3:
   orientation readings with the thesis' noise); compensation minimises
   |log(R_t^T R)|^2 + (w (|p| - s_t))^2 (`kiwibot.pointing_residual`, Gauss-Newton
   `compensate.least_squares`); the settings are commanded on the true robot.
2. The fast approximate method of §3.2/§4.4.4 (`compensate.line_search`) against the exact one.
3. The Delta's real-experiment analysis (§4.4.4, Figs 4.41-4.42) and the simulations' figures
   (4.34-4.40): true robot = Table 4.7's perturbed model (rod 26 +20 mm); calibrated models =
   perturbed + each printed column of Table 4.7; exact (`compensate.compensate`, Newton) and fast
   compensation on the 125-point grid; worst position error and largest nacelle rotation against
   the nominal nacelle (its orientation cannot be controlled). The rounding of Table 4.7 (2 digits)
   is propagated by drawing each printed entry uniformly within its last digit.
4. Table A.1 (App. A.5): the normalised eigenvalue metric e(A; A + kE) under one hypothesis.

Run: python benchmarks/seed004_compensation.py   (prints "quantity | thesis | ours | why they differ")
"""

from __future__ import annotations

import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import median_time  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.closure import closed  # noqa: E402
from jaxcal.closure import delta as dl  # noqa: E402
from jaxcal.closure import kiwibot as kb  # noqa: E402
from jaxcal.fit.compensate import compensate, least_squares, line_search  # noqa: E402
from jaxcal.kin.rotations import log_so3  # noqa: E402

ROWS = []  # (quantity, thesis, ours, why)


def row(quantity, thesis, ours, why=""):
    ROWS.append((quantity, thesis, ours, why))


def pose_errors(robot, a_true, q, p_ref, R_ref):
    """Worst |p - p_ref| (mm), RMS (mm), largest rotation angle of R_ref^T R (deg) of the true robot at q."""
    pose = jc.forward(robot, a_true, q)
    e = np.linalg.norm(np.asarray(pose.p - p_ref), axis=-1) * 1e3
    ang = np.degrees(np.linalg.norm(np.asarray(jax.vmap(lambda R, Rr: log_so3(Rr.T @ R))(pose.R, R_ref)), axis=-1))
    return float(e.max()), float(np.sqrt(np.mean(e**2))), float(ang.max())


# -- Kiwibot -----------------------------------------------------------------------------------
def kiwibot_model(rb, a_true, column):
    """Perturbed + Table 4.5 identified - perturbed column (3, 4, 5 = sims 1, 2, 3; lost entry -> 0)."""
    a = np.array(a_true)
    for r in kb.TABLE_4_5:
        a[rb.index(r[0])] += r[column] or 0.0
    return jnp.asarray(a)


def kiwibot():
    rb = jc.robots.get("kiwibot")
    a_true = kb.thesis_perturbed(rb)
    q0, _ = kb.hemisphere_grid(160)
    q0 = jnp.asarray(q0)
    target = jax.vmap(kb.direct)(q0)
    strut = jnp.linalg.norm(target.p, axis=-1)

    def residual(a, w, R, s):
        return lambda q: kb.pointing_residual(jc.forward(rb, a, q), R, s, w)

    exact = jax.jit(lambda a, w: jax.vmap(lambda R, s, q: least_squares(residual(a, w, R, s), q))(target.R, strut, q0))
    fast = jax.jit(lambda a: jax.vmap(lambda R, s, q: line_search(residual(a, kb.STRUT_WEIGHT, R, s), q))(target.R, strut, q0))

    def judged(q):
        worst, _, ang = pose_errors(rb, a_true, q, target.p, target.R)
        drift = float(np.max(np.abs(np.linalg.norm(np.asarray(jc.forward(rb, a_true, q).p), axis=-1) - np.asarray(strut)))) * 1e3
        return worst, ang, drift

    worst, ang, _ = judged(q0)
    why_grid = "thesis' 160 settings (Fig 4.22) not in the text; ours: hemisphere at 0.7 m strut"
    row("Kiwibot, nominal settings on true robot: worst position / largest angle (Figs 4.23, 4.25)", "3.18 mm / 0.535 deg",
        f"{worst:.2f} mm / {ang:.3f} deg", why_grid)
    data = jc.simulate(rb, a_true, q0, "orientation", noise={"orientation": float(np.sqrt(1.28e-9)),
                                                             "actuator": float(np.sqrt(1.31e-9))}, seed=0)
    ours = jc.identify(rb, data, known=("dev", "tool"), sigma_orientation=float(np.sqrt(1.28e-9))).a
    thesis = {"sim 1 (Figs 4.24, 4.26)": ("? (lost) / 0.0519 deg", 3), "sim 2 (Figs 4.27-4.28)": ("3.92 mm / 0.0518 deg", 4),
              "sim 3 (Figs 4.29-4.30)": ("3.89 mm / 0.0524 deg", 5)}
    for label, (printed, column) in thesis.items():
        worst, ang, drift = judged(exact(kiwibot_model(rb, a_true, column), kb.STRUT_WEIGHT))
        row(f"Kiwibot, compensated with thesis' Table 4.5 {label}: worst position / largest angle", printed,
            f"{worst:.2f} mm / {ang:.4f} deg (strut kept to {drift:.3f} mm)", why_grid)
    worst, ang, drift = judged(exact(ours, kb.STRUT_WEIGHT))
    row("Kiwibot, compensated with our sim-3 identification", "(sim 3) 3.89 mm / 0.0524 deg",
        f"{worst:.2f} mm / {ang:.4f} deg (strut kept to {drift:.3f} mm)", why_grid)
    q = exact(a_true, 0.0)
    ok = np.asarray(closed(rb, a_true, q))
    drift = np.abs(np.linalg.norm(np.asarray(jc.forward(rb, a_true, q).p), axis=-1) - np.asarray(strut))[ok] * 1e3
    row("Kiwibot, true model, no strut bias (w = 0): strut-length change", "up to 600 mm",
        f"{len(q) - ok.sum()} of {len(q)} settings leave the workspace (do not close); the rest: median "
        f"{np.median(drift):.0f} mm, max {drift.max():.0f} mm",
        "an orientation is reachable at any strut length; without the bias Gauss-Newton runs off along it")
    worst, ang, drift = judged(fast(ours))
    row("Kiwibot, fast method (one line search) with our model", "not reported", f"{worst:.2f} mm / {ang:.4f} deg", "")
    t_exact = median_time(lambda: jax.block_until_ready(exact(ours, kb.STRUT_WEIGHT)), repeat=3) / len(q0)
    t_fast = median_time(lambda: jax.block_until_ready(fast(ours)), repeat=3) / len(q0)
    row("Kiwibot compensation time per target, exact (8 GN steps) / fast", "not reported",
        f"{t_exact * 1e3:.2f} ms / {t_fast * 1e3:.2f} ms", "vmapped over 160 targets, after compile, this CPU")


# -- Delta -------------------------------------------------------------------------------------
def rounded_draw(rng, value):
    """value with its printed last (second significant) digit replaced by a uniform draw within it."""
    if value == 0:
        return 0.0
    unit = 10.0 ** (np.floor(np.log10(abs(value))) - 1)
    return value + rng.uniform(-0.5, 0.5) * unit


def delta():
    rb = jc.robots.get("delta")
    a_true = dl.thesis_perturbed(rb)
    P = jnp.asarray(dl.grid())
    q0 = jax.vmap(dl.inverse)(P)[0]
    R_ref = jc.forward(rb, rb.nominal, q0).R  # nominal nacelle orientation at the nominal settings

    def fast(a):
        return jax.vmap(lambda p, q: line_search(lambda x: jc.forward(rb, a, x).p - p, q))(P, q0)

    fast = jax.jit(fast)
    worst, rms, ang = pose_errors(rb, a_true, q0, P, R_ref)
    row("Delta, nominal settings on rod-26 +20 mm robot: largest nacelle rotation (Fig 4.34)", "5.162 deg", f"{ang:.3f} deg", "")
    row("Delta, same: worst position error (Fig 4.33)", "caption lost", f"{worst:.2f} mm (RMS {rms:.2f})", "")
    printed = {"sim1": ("lost / 5.010 deg", "Figs 4.35-4.36"), "sim2": ("2.987 mm / 4.997 deg", "Figs 4.37-4.38"),
               "sim3": ("3.681 mm / 4.994 deg", "Figs 4.39-4.40"), "experiment": ("9.322 mm / 5.056 deg", "Figs 4.41-4.42")}
    for column, (thesis, figs) in printed.items():
        worst, rms, ang = pose_errors(rb, a_true, compensate(rb, dl.thesis_identified(rb, column), P, start=q0).q, P, R_ref)
        why = ("printed columns 5-6 do not give the figures' position errors (column 6 is ~2 x column 5 entry by "
               "entry): not the models behind Figs 4.37/4.39, or a column mix-up") if column in ("sim2", "sim3") else ""
        row(f"Delta, exact compensation with Table 4.7 {column} ({figs}): worst position / largest angle", thesis,
            f"{worst:.2f} mm (RMS {rms:.2f}) / {ang:.3f} deg", why)
    a_exp = dl.thesis_identified(rb, "experiment")
    shifted = []
    for z in (-0.95, -1.05):
        Pz = jnp.asarray(dl.grid(center=(0.0, 0.0, z)))
        qz = jax.vmap(dl.inverse)(Pz)[0]
        shifted.append(pose_errors(rb, a_true, compensate(rb, a_exp, Pz, start=qz).q, Pz, R_ref)[0])
    row("Delta, experiment, exact: worst position with the grid centred 50 mm higher / lower", "9.322 mm",
        f"{shifted[0]:.2f} mm / {shifted[1]:.2f} mm", "the grid's height is not printed (ours: centre at z = -1.0 m)")
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(40):
        a = np.array(a_true)
        for r in dl.TABLE_4_7:
            a[rb.index(r[0])] += rounded_draw(rng, r[4])
        draws.append(pose_errors(rb, a_true, compensate(rb, jnp.asarray(a), P, start=q0).q, P, R_ref)[0])
    lo, hi = np.percentile(draws, [5, 95])
    row("Delta, experiment, exact: worst position over the rounding of Table 4.7 (40 draws, 5-95 %)", "9.322 mm",
        f"{lo:.2f}-{hi:.2f} mm", "rounding explains it" if lo <= 9.322 <= hi else
        "rounding does not explain the gap (see docs/seed004-compensation.md)")
    worst, rms, ang = pose_errors(rb, a_true, fast(a_exp), P, R_ref)
    row("Delta, experiment, fast method (one line search): worst position / angle", "13.4 mm / -",
        f"{worst:.2f} mm (RMS {rms:.2f}) / {ang:.3f} deg", "line-search offsets not printed (ours: s, 2s, s = f0/|g|^2)")
    model_err = float(jnp.max(jnp.linalg.norm(jc.forward(rb, a_exp, fast(a_exp)).p - P, axis=-1))) * 1e3
    row("Delta, experiment, fast method: worst error left in the calibrated model itself", "-", f"{model_err:.2f} mm",
        "exact: < 1e-6 mm")
    t_exact = median_time(lambda: jax.block_until_ready(compensate(rb, a_exp, P, start=q0).q), repeat=3) / len(P)
    t_fast = median_time(lambda: jax.block_until_ready(fast(a_exp)), repeat=3) / len(P)
    row("Delta compensation time per point, exact (6 Newton steps) / fast", "20 s / 6 s (17.7 / 4.5 MFlops, MATLAB)",
        f"{t_exact * 1e3:.3f} ms / {t_fast * 1e3:.3f} ms", "vmapped over 125 points, after compile, this CPU")


# -- Table A.1 ---------------------------------------------------------------------------------
TABLE_A1_K1 = (1.0, 0.49, 0.29, 0.19, 0.12, 0.084, 0.058)  # row k = 1, n = 2 ... 160 (scales linearly with k)


def table_a1(draws=20, seed=0):
    """Hypothesis: A = I (lambda_M = 1), E = X X^T / trace (X n x n Gaussian): e(A; A + kE) = k |eig(E)|_2,
    exactly linear in k as the printed table is. Mean over `draws` for n = 2 ... 160."""
    rng = np.random.default_rng(seed)
    out = []
    for n in (2, 5, 10, 20, 40, 80, 160):
        vals = []
        for _ in range(draws):
            X = rng.standard_normal((n, n))
            E = X @ X.T
            vals.append(np.linalg.norm(np.linalg.eigvalsh(E / np.trace(E))))
        out.append(float(np.mean(vals)))
    row("Table A.1, k = 1, n = 2 5 10 20 40 80 160", " ".join(f"{v:.2g}" for v in TABLE_A1_K1),
        " ".join(f"{v:.2g}" for v in out),
        "test matrix A, the law of E and the norm ||E|| = 1 are not printed; hypothesis A = I, E Wishart / trace")


def main():
    t = time.perf_counter()
    delta()
    table_a1()
    kiwibot()
    print("\n| quantity | thesis | ours | why they differ |\n|---|---|---|---|")
    for r in ROWS:
        print("| " + " | ".join(r) + " |")
    print(f"\n({time.perf_counter() - t:.0f} s)")


if __name__ == "__main__":
    main()
