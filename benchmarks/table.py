"""`make bench`: the benchmark table of docs/benchmarks.md in one run, every row a ratio against a baseline
measured in the same process, compile time apart, medians.

- forward kinematics: jaxcal's jit(vmap) vs the hand-vectorised numpy model and a Python loop (benchmarks/fk.py);
- identification: the whole `jc.identify` call and its core run (`timings["run_s"]`: start, base set, solves, final
  Jacobian) vs scipy's MINPACK LM with finite differences on the same unknowns from the same start
  (benchmarks/identify.py), with jaxcal's LM and optimistix's;
- forward kinematics and the joint Jacobian of the real TALOS arm's URDF vs pinocchio (`pip install pin`, which
  `make bench` installs), called per configuration from Python (benchmarks/pinocchio_fk.py);
- identification of the real TALOS arm (61 mocap positions) and of the Delta (125 simulated positions), default
  options: the whole `jc.identify` call vs scipy's MINPACK LM with finite differences on jaxcal's own compiled
  residual, same unknowns (the ones identify estimated), same start (identify's frames-only point).

Writes benchmarks/results/bench.md and, when every part ran, the table of docs/benchmarks.md (the lines between
DOCS_START and DOCS_END), both atomically, and prints its rows as they come. Run: python benchmarks/table.py
[--max-n N] [--parts fk,pinocchio,identify,own] [--out FILE] [--docs FILE, '' to leave the docs as they are]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import fk
import identify
import jax
import numpy as np
import pinocchio_fk
import scipy.optimize
from _common import first_and_median, median_time

import jaxcal as jc
from jaxcal.fit import core
from jaxcal.report import write_text_atomic

DOCS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "benchmarks.md")
DOCS_START = "<!-- make bench: the table below is written by benchmarks/table.py -->"
DOCS_END = "<!-- make bench: end of the table -->"


def spliced(doc: str, block: str, source: str) -> str:
    """doc with the lines between its DOCS_START and DOCS_END lines replaced by block (the marker lines and the rest
    kept as they are). ValueError naming source when a marker is missing, repeated or out of order."""
    lines = doc.splitlines(keepends=True)
    starts = [i for i, line in enumerate(lines) if line.strip() == DOCS_START]
    ends = [i for i, line in enumerate(lines) if line.strip() == DOCS_END]
    if len(starts) != 1 or len(ends) != 1 or ends[0] < starts[0]:
        raise ValueError(f"{source}: needs one line {DOCS_START!r} and, after it, one line {DOCS_END!r} around the table "
                         f"(found {len(starts)} and {len(ends)})")
    return "".join(lines[:starts[0] + 1]) + block.rstrip("\n") + "\n" + "".join(lines[ends[0]:])


def machine_line() -> str:
    load = os.getloadavg()
    device = jax.devices()[0]
    return (f"{datetime.date.today()}, {platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on "
            f"{device.platform} ({device.device_kind}), load average at the start {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")


def fk_rows(max_n: int) -> list[str]:
    rows = []
    for n, compile_s, t_jax, t_np, t_loop in fk.main(max_n):
        loop = f"{t_loop / t_jax:.0f}x" if t_loop == t_loop else ""
        rows.append(f"| FK, Stanford, N = {n:.0e} | {compile_s:.2f} s | {t_jax * 1e3:.2f} ms | numpy {t_np * 1e3:.2f} ms "
                    f"| {t_np / t_jax:.1f}x | {loop} |")
    return rows


def pinocchio_rows(n: int = 10_000) -> list[str]:
    rows = []
    for r in pinocchio_fk.main(n):
        if r["t_pin"] != r["t_pin"]:
            rows.append(f"| {r['what']}, TALOS left arm URDF, N = {n:.0e} | {r['compile_s']:.2f} s | {r['t_jc'] * 1e3:.2f} ms "
                        f"| pinocchio not installed (`pip install pin`) | | |")
            continue
        rows.append(f"| {r['what']}, TALOS left arm URDF, N = {n:.0e} | {r['compile_s']:.2f} s | {r['t_jc'] * 1e3:.2f} ms "
                    f"| pinocchio, a Python loop over its C++ call: {r['t_pin'] * 1e3:.1f} ms "
                    f"({r['t_pin'] / n * 1e6:.2f} us a configuration) | {r['t_pin'] / r['t_jc']:.1f}x | agree to 1e-12 |")
    return rows


def identify_rows() -> list[str]:
    rows = []
    for kind, noise in (("position", 2e-5), ("pose", {"position": 2e-5, "orientation": 2e-5})):
        for solver in ("lm", "lm_optimistix"):
            r = identify.run_case(kind, noise, solver=solver)
            rows.append(f"| identify, Stanford 200 {kind}, {r['n_est']} parameters, solver {solver} "
                        f"| {r['compile_s']:.2f} s (first call {r['first_s']:.2f} s) "
                        f"| call {r['t_jc'] * 1e3:.1f} ms (core run {r['t_solve'] * 1e3:.1f} ms) "
                        f"| scipy LM + FD {r['t_scipy'] * 1e3:.1f} ms "
                        f"| call {r['t_scipy'] / r['t_jc']:.1f}x, core run {r['t_scipy'] / r['t_solve']:.1f}x "
                        f"| RMS {r['rms_jc']:.5f} vs {r['rms_scipy']:.5f} mm |")
    return rows


def scipy_on_own_residual(robot, data, fit, sigma, repeat: int):
    """(seconds, RMS mm, residual evaluations): scipy least_squares(method="lm", 2-point FD, unbiased, at most 50
    Jacobians) over the entries `fit` estimated, from identify's frames-only point, on `core.weighted_residuals`
    (jaxcal's compiled residual, one call per FD column)."""
    start = np.asarray(jc.identify(robot, data, free=(), sigma_position=sigma).a_full)
    idx = fit.info["estimated_index"]
    w = fit.device.weights(sigma, sigma)

    def res(x):
        a = start.copy()
        a[idx] = x
        return core.weighted_residuals(robot, fit.device, a, data.q, data.y, w).reshape(-1)

    out = {}
    t = median_time(lambda: out.update(sol=scipy.optimize.least_squares(res, start[idx], method="lm",
                                                                         max_nfev=50 * (len(idx) + 1))), repeat=repeat)
    return t, float(np.sqrt(np.mean(out["sol"].fun ** 2)) * sigma * 1e3), out["sol"].nfev


def own_residual_rows() -> list[str]:
    talos = jc.realdata.load("talos")
    delta = jc.robots.get("delta")
    q = jc.random_configurations(delta, 125, seed=2)
    delta_data = jc.simulate(delta, jc.perturb(delta, 1e-3, seed=1), q, device="position", noise=1e-5, seed=3)
    rows = []
    # the Delta's call takes a few hundred ms (its noise-dominated fit chooses the bias by 4-fold held-out error): the
    # median of 3 calls after the first; scipy's 100 s on it once. TALOS: 15 calls (its 50 ms vary by 10-30 %)
    for label, robot, data, repeat, repeat_sp in (("TALOS left arm, 61 real mocap positions", talos.robot, talos.data, 15, 3),
                                                  ("Delta (Table 4.6), 125 positions, 0.01 mm noise", delta, delta_data, 3, 1)):
        fit, first, t = first_and_median(lambda: jc.identify(robot, data, sigma_position=1e-3), repeat=repeat)
        t_sp, rms_sp, nfev = scipy_on_own_residual(robot, data, fit, 1e-3, repeat=repeat_sp)
        rows.append(f"| identify, {label}, {len(fit.estimated)} parameters, default options | first call {first:.1f} s "
                    f"| call {t * 1e3:.0f} ms ({fit.iterations} LM steps) | scipy LM + FD on jaxcal's residual, unbiased, "
                    f"{t_sp * 1e3:.0f} ms ({nfev} evaluations) | {t_sp / t:.1f}x | RMS {fit.rms_after:.4f} vs {rms_sp:.4f} mm |")
    return rows


PARTS = {"fk": fk_rows, "pinocchio": pinocchio_rows, "identify": identify_rows, "own": own_residual_rows}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-n", type=int, default=100_000, help="largest FK batch (default 1e5)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench.md"))
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {', '.join(PARTS)} (default all)")
    ap.add_argument("--docs", default=DOCS, help="the Markdown file whose table a run of every part rewrites ('' for none)")
    args = ap.parse_args(argv)
    parts = args.parts.split(",")
    if unknown := sorted(set(parts) - set(PARTS)):
        ap.error(f"--parts: unknown {', '.join(unknown)}; choose from {', '.join(PARTS)}")
    docs = args.docs if args.docs and sorted(parts) == sorted(PARTS) else None
    if docs:  # a file without its markers fails now, not after the run
        with open(docs, encoding="utf-8") as f:
            spliced(f.read(), "", docs)
    t0 = time.perf_counter()
    head = [f"Machine: {machine_line()}.", "",
            "| case | compile | jaxcal (median) | baseline, same process (median) | speed-up | other |",
            "|---|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    rows = []
    for part in parts:
        new = PARTS[part](args.max_n) if part == "fk" else PARTS[part]()
        print("\n".join(new), flush=True)  # as they come: a run stopped part-way still shows its rows
        rows += new
    text = "\n".join(head + rows + ["", f"Whole run {time.perf_counter() - t0:.0f} s.", ""])
    write_text_atomic(args.out, text)
    written = [args.out]
    if docs:
        with open(docs, encoding="utf-8") as f:
            write_text_atomic(docs, spliced(f.read(), text, docs))
        written.append(docs)
    print(f"Whole run {time.perf_counter() - t0:.0f} s; written to {' and '.join(written)}"
          + ("" if docs or not args.docs else f" ({args.docs} left as it is: --parts ran a subset)"))


if __name__ == "__main__":
    main()
