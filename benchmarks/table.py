"""`make bench`: the benchmark table of docs/benchmarks.md in one run, every row a ratio against a baseline
measured in the same process, compile time apart, medians.

- forward kinematics: jaxcal's jit(vmap) vs the hand-vectorised numpy model and a Python loop (benchmarks/fk.py);
- identification: the whole `jc.identify` call and its core run (`timings["run_s"]`: start, base set, solves, final
  Jacobian) vs scipy's MINPACK LM with finite differences on the same unknowns from the same start
  (benchmarks/identify.py), with jaxcal's LM and optimistix's.

Writes benchmarks/results/bench.md (atomically) and prints it. Run: python benchmarks/table.py [--max-n N]
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

from jaxcal.report import write_text_atomic


def machine_line() -> str:
    load = os.getloadavg()
    return (f"{datetime.date.today()}, {platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} on "
            f"{jax.devices()[0].platform}, load average at the start {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")


def fk_rows(max_n: int) -> list[str]:
    rows = []
    for n, compile_s, t_jax, t_np, t_loop in fk.main(max_n):
        loop = f"{t_loop / t_jax:.0f}x" if t_loop == t_loop else ""
        rows.append(f"| FK, Stanford, N = {n:.0e} | {compile_s:.2f} s | {t_jax * 1e3:.2f} ms | numpy {t_np * 1e3:.2f} ms "
                    f"| {t_np / t_jax:.1f}x | {loop} |")
    return rows


def identify_rows() -> list[str]:
    rows = []
    for kind, noise in (("position", 2e-5), ("pose", {"position": 2e-5, "orientation": 2e-5})):
        for solver in ("lm", "lm_optimistix"):
            r = identify.run_case(kind, noise, solver=solver)
            rows.append(f"| identify, Stanford 200 {kind}, {r['n_est']} parameters, solver {solver} | {r['compile_s']:.2f} s "
                        f"| call {r['t_jc'] * 1e3:.1f} ms (core run {r['t_solve'] * 1e3:.1f} ms) "
                        f"| scipy LM + FD {r['t_scipy'] * 1e3:.1f} ms "
                        f"| call {r['t_scipy'] / r['t_jc']:.1f}x, core run {r['t_scipy'] / r['t_solve']:.1f}x "
                        f"| RMS {r['rms_jc']:.5f} vs {r['rms_scipy']:.5f} mm |")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-n", type=int, default=100_000, help="largest FK batch (default 1e5)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench.md"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    head = [f"Machine: {machine_line()}.", "",
            "| case | compile | jaxcal (median) | baseline, same process (median) | speed-up | other |",
            "|---|---|---|---|---|---|"]
    rows = fk_rows(args.max_n) + identify_rows()
    text = "\n".join(head + rows + ["", f"Whole run {time.perf_counter() - t0:.0f} s.", ""])
    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
