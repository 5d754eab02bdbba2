"""Monte Carlo identification throughput only (no studies): vmapped vs a loop of the same jitted
solve, for a given number of runs. Used on the GPU machine as well as here.

Run: python benchmarks/mc_speed.py [--runs 64 256 1024] [--robots mrr1 stanford]
"""

from __future__ import annotations

import argparse

import jax
from montecarlo import speed


def main(runs_list, robots, solver=None):
    print(f"jax {jax.__version__} on {jax.devices()}")
    print(f"solver {solver or 'default'}")
    print(f"{'robot':<10}{'runs':>6}{'params':>7}{'compile s':>10}{'vmap id/s':>11}{'loop id/s':>11}{'ratio':>7}")
    for name in robots:
        for runs in runs_list:
            mc, loop_rate = speed(name, runs, solver)
            rate = runs / mc.timings["run_s"]
            print(f"{name:<10}{runs:>6}{len(mc.names):>7}{mc.timings['compile_s']:>10.1f}{rate:>11.1f}{loop_rate:>11.1f}"
                  f"{rate / loop_rate:>7.1f}", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, nargs="+", default=[64, 256])
    ap.add_argument("--robots", nargs="+", default=["mrr1", "stanford"])
    ap.add_argument("--solver", default=None, help="Monte Carlo solver (default: monte_carlo's choice)")
    a = ap.parse_args()
    main(a.runs, a.robots, a.solver)
