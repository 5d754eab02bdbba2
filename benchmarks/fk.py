"""Forward-kinematics throughput: jit(vmap(forward)) vs hand-vectorised numpy vs a Python loop.

Stanford arm (seed 001 Table 1), N = 1e3 .. 1e6 configurations, one process. Compile time is
reported apart; run times are medians. Run: python benchmarks/fk.py [--max-n 1000000]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import median_time, stanford_fk_numpy

import jaxcal as jc
from jaxcal.kin.model import forward_open


def main(max_n: int = 1_000_000):
    rb = jc.robots.get("stanford")
    a = jnp.asarray(jc.perturb(rb, 0.01, seed=1))
    a_np = np.asarray(a)
    fk = jax.jit(lambda a, q: forward_open(rb, a, q))
    one = jax.jit(lambda a, q: forward_open(rb, a, q))
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    print(f"{'N':>9} {'compile s':>10} {'jax ms':>10} {'numpy ms':>10} {'loop ms':>10}"
          f" {'jax Mcfg/s':>11} {'jax/numpy':>10} {'jax/loop':>9}")
    rows = []
    q_one = jnp.asarray(jc.random_configurations(rb, 1, seed=0)[0])
    one(a, q_one)[1].block_until_ready()
    n = 1000
    while n <= max_n:
        q = jc.random_configurations(rb, n, seed=n)
        qj = jnp.asarray(q)
        t = time.perf_counter()
        fk(a, qj)[1].block_until_ready()
        compile_s = time.perf_counter() - t
        t_jax = median_time(lambda: fk(a, qj)[1].block_until_ready(), repeat=5)
        R, p = stanford_fk_numpy(a_np, q)
        np.testing.assert_allclose(np.asarray(fk(a, qj)[1]), p, atol=1e-12)
        t_np = median_time(lambda: stanford_fk_numpy(a_np, q), repeat=3)
        if n <= 1000:
            t_loop = median_time(lambda: [one(a, qi)[1].block_until_ready() for qi in qj], repeat=3)
        else:
            t_loop = float("nan")
        rows.append((n, compile_s, t_jax, t_np, t_loop))
        print(f"{n:>9} {compile_s:>10.2f} {t_jax * 1e3:>10.2f} {t_np * 1e3:>10.2f} {t_loop * 1e3:>10.1f} "
              f"{n / t_jax / 1e6:>11.2f} {t_np / t_jax:>10.1f} {t_loop / t_jax:>9.0f}")
        n *= 10
    print("(compile s includes tracing for the new N; the loop calls the jitted single-configuration FK per row;"
          " loop timed at N = 1e3 only)")
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--max-n", type=int, default=1_000_000)
    main(ap.parse_args().max_n)
