"""Four-bar loop closures per second: vmapped closure (solve) and closed forward + jacfwd, after compile.

fourbar2d (seed 004 §2.5) and fourbar3d (Table 4.2a) at 125 and 10,000 actuator settings, with the
optimistix Levenberg-Marquardt closure ("lm", default) and the Newton/LM hybrid ("newton"), one
process. Compile time is reported apart (first call, which also traces; the persistent compilation
cache may shorten it); run times are medians. Starts are the robots' default assembly-mode starts.
Run: python benchmarks/closure_fourbar.py [--sizes 125 10000]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
from _common import median_time

import jaxcal as jc
from jaxcal.closure import solve


def _with_solver(rb, solver):
    return rb.replace(closure=dataclasses.replace(rb.closure, solver=solver))


def _timed(fn):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    compile_s = time.perf_counter() - t
    return compile_s, median_time(lambda: jax.block_until_ready(fn()), repeat=5)


def main(sizes=(125, 10_000)):
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    print(f"{'robot':<10}{'solver':<8}{'N':>7}{'compile s':>11}{'solve ms':>10}{'closures/s':>12}{'max steps':>10}"
          f"{'all ok':>8}{'jac compile s':>14}{'jac ms (N=125)':>15}")
    for name in ("fourbar2d", "fourbar3d"):
        base = jc.robots.get(name)
        a = jc.perturb(base, 1e-3, seed=1)
        base_rate = None
        for solver in ("lm", "newton"):
            rb = _with_solver(base, solver)
            jac = jax.jit(jax.jacfwd(lambda a_, q_, rb=rb: jc.forward(rb, a_, q_).p))
            for n in sizes:
                q = jnp.asarray(jc.random_configurations(rb, n, seed=n))
                compile_s, t = _timed(lambda rb=rb, q=q: solve(rb, a, q))
                sol = solve(rb, a, q)
                jac_c, jac_t = _timed(lambda q=q[:125]: jac(a, q)) if n == sizes[0] else (float("nan"), float("nan"))
                rate = n / t
                if solver == "lm" and n == sizes[-1]:
                    base_rate = rate
                print(f"{name:<10}{solver:<8}{n:>7}{compile_s:>11.2f}{t * 1e3:>10.2f}{rate:>12.0f}{int(sol.steps.max()):>10}"
                      f"{str(bool(sol.ok.all())):>8}{jac_c:>14.2f}{jac_t * 1e3:>15.2f}")
            if solver == "newton" and base_rate:
                print(f"{'':<10}newton/lm closures/s ratio at N={sizes[-1]}: {rate / base_rate:.2f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[125, 10_000])
    main(tuple(parser.parse_args().sizes))
