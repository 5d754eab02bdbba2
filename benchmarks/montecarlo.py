"""Vectorised Monte Carlo identification (seed 004 §4.3.1): speed and the noise studies.

1. Identifications per second: one vmapped compiled LM over the noise draws vs a Python loop of
   the same jitted single solve, same process; compile apart; 1 vs 2 host devices (subprocess
   with XLA_FLAGS=--xla_force_host_platform_device_count=2); peak memory (max RSS).
2. Studies like Figures 4.12-4.14 and 4.19: residual norm vs measurement noise, vs actuator
   noise, vs number of measurements; chi-square Q-Q plot; the Table 4.3 comparison of linear and
   Monte Carlo covariances. Run on every built-in the engine has among "fourbar3d", "mrr1" and
   "stanford". Plots go to bench-output/montecarlo/. The four-bar with the thesis' own settings
   (Table 4.2b truth, the ten Table 4.2c noise runs, Table 4.3) is benchmarks/montecarlo_fourbar3d.py.

Run: python benchmarks/montecarlo.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxcal as jc
from jaxcal.fit import core
from jaxcal.fit import uncertainty as un
from jaxcal.fit.identify import residual_weights

OUT = os.path.join("bench-output", "montecarlo")
CASES = {  # robot -> (device, known device parameters, n configurations, noise sd)
    "fourbar3d": ("pose", ("dev", "tool"), 30, 5e-5),
    "mrr1": ("pose", ("dev",), 30, 1e-5),
    "stanford": ("position", (), 60, 2e-5),
}


def _noise(device, s, s_q=0.0):
    return {"position": s, "orientation": s if device == "pose" else 0.0, "actuator": s_q}


def speed(name, runs, solver=None):
    device, known, n, s = CASES[name]
    rb = jc.robots.get(name)
    a = jc.perturb(rb, 0.003, seed=1)
    q = jc.random_configurations(rb, n, seed=2, margin=0.05)
    mc = un.monte_carlo(rb, a, q, device, noise=_noise(device, s), runs=runs, known=known, chunk=runs,
                        sigma_position=s, sigma_orientation=s, devices=[], solver=solver)
    # the same solve (same solver, start, weights), one noise draw at a time, in a Python loop
    ref = jc.identify(rb, jc.simulate(rb, a, q, device), known=known, sigma_position=s, sigma_orientation=s)
    dev = jc.make_device(device)
    idx = ref.info["estimated_index"]
    mask = np.zeros(len(ref.names))
    mask[idx] = 1
    a0 = jnp.asarray(ref.a_full)
    n_loop = min(runs, 32)
    datas = [jc.simulate(rb, a, q, device, noise=_noise(device, s), seed=100 + i) for i in range(n_loop)]
    problem = core.make_problem(rb, dev, q, datas[0].y, weights=residual_weights(dev, s, s), free=mask > 0, a_ref=np.asarray(a0))
    args = dict(problem.args(idx, 0.0, np.asarray(a0)), w=jnp.asarray(problem.w))
    settings = core.Settings(mc.timings["solver"], 50, 1e-8, 1e-10)
    exe, _ = core.compiled_solver(a0, args, rb, dev, settings)
    t = time.perf_counter()
    for d in datas:
        jax.block_until_ready(exe(a0, {**args, "y": jnp.asarray(d.y)}, core.step_limit(settings.max_steps)))
    loop_rate = n_loop / (time.perf_counter() - t)
    return mc, loop_rate


def two_devices(name, runs):
    code = (f"import sys; sys.path.insert(0, 'benchmarks'); import montecarlo as m, jax; "
            f"import jaxcal as jc; from jaxcal.fit import uncertainty as un; "
            f"dev, known, n, s = m.CASES[{name!r}]; rb = jc.robots.get({name!r}); a = jc.perturb(rb, 0.003, seed=1); "
            f"q = jc.random_configurations(rb, n, seed=2, margin=0.05); "
            f"r = un.monte_carlo(rb, a, q, dev, noise=m._noise(dev, s), runs={runs}, known=known, chunk={runs}, "
            f"sigma_position=s, sigma_orientation=s, devices=jax.devices()); "
            f"print('RATE', {runs} / r.timings['run_s'], r.timings['devices'])")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=1800)
    for line in out.stdout.splitlines():
        if line.startswith("RATE"):
            return float(line.split()[1])
    raise RuntimeError(out.stderr[-2000:])


def studies(name, runs, quick):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxcal.report import save_atomic

    device, known, n, s = CASES[name]
    rb = jc.robots.get(name)
    a = jc.perturb(rb, 0.003, seed=1)
    q = jc.random_configurations(rb, n, seed=2, margin=0.05)
    levels = [1e-6, 1e-5, 1e-4] if quick else [1e-7, 1e-6, 1e-5, 1e-4, 1e-3]
    res_m = []
    for sm in levels:  # Figure 4.12: residual norm vs measurement noise (weights 1: plain norm, m and rad)
        mc = un.monte_carlo(rb, a, q, device, noise=_noise(device, sm), runs=runs, known=known, chunk=runs,
                            sigma_position=1.0, sigma_orientation=1.0, devices=[])
        res_m.append(np.median(mc.residual_norms))
    res_q = []
    for sq in levels:  # Figure 4.13: vs actuator noise
        mc = un.monte_carlo(rb, a, q, device, noise=_noise(device, 0.0, sq), runs=runs, known=known, chunk=runs,
                            sigma_position=1.0, sigma_orientation=1.0, devices=[])
        res_q.append(np.median(mc.residual_norms))
    counts = [10, 20, 40] if quick else [8, 12, 20, 40, 80]
    res_n = []
    q_test = jnp.asarray(jc.random_configurations(rb, 50, seed=9, margin=0.05))
    true_tip = jc.forward(rb, jnp.asarray(a), q_test).p
    for k in counts:  # Figure 4.14: model error of the identified robot vs number of measurements (noise 1e-5)
        qk = jc.random_configurations(rb, k, seed=3, margin=0.05)
        mc = un.monte_carlo(rb, a, qk, device, noise=_noise(device, 1e-5), runs=runs, known=known, chunk=runs,
                            sigma_position=1e-5, sigma_orientation=1e-5, devices=[])
        idx = [rb.index(n) for n in mc.names if n in rb.names]
        cols = [i for i, n in enumerate(mc.names) if n in rb.names]
        base = np.asarray(jc.identify(rb, jc.simulate(rb, a, qk, device), known=known).a)
        errs = []
        for row in mc.estimates[mc.converged]:
            a_est = base.copy()
            a_est[idx] = row[cols]
            errs.append(np.sqrt(np.mean(np.sum((jc.forward(rb, jnp.asarray(a_est), q_test).p - true_tip) ** 2, -1))))
        res_n.append(np.median(errs))
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.6))
    axs[0].loglog(levels, res_m, "o-")
    axs[0].set(xlabel="measurement noise sd", ylabel="residual 2-norm after identification", title="cf. Figure 4.12")
    axs[1].loglog(levels, res_q, "o-")
    axs[1].set(xlabel="actuator noise sd [rad or m]", title="cf. Figure 4.13")
    axs[2].semilogy(counts, res_n, "o-")
    axs[2].set(xlabel="number of measurements", ylabel="tool position error of the model [m]",
               title="cf. Figure 4.14 (noise 1e-5, 50 test poses)")
    for ax in axs:
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"{name}: {runs} Monte Carlo identifications per point")
    save_atomic(fig, os.path.join(OUT, f"{name}_residual_studies.png"))
    # Figure 4.19: chi-square plot of the estimates
    mc = un.monte_carlo(rb, a, q, device, noise=_noise(device, s), runs=max(runs, 200), known=known, chunk=max(runs, 200),
                        sigma_position=s, sigma_orientation=s, devices=[])
    d2, quant, corr = un.chi2_qq(mc.estimates[mc.converged & mc.keep])
    fig, ax = plt.subplots(figsize=(4.5, 4.2))
    ax.plot(quant, d2, ".", ms=4)
    ax.plot(quant, quant, "k-", lw=1)
    ax.set(xlabel="chi-square quantile", ylabel="sorted Mahalanobis d^2", title=f"{name}: chi-square plot (r = {corr:.3f})")
    save_atomic(fig, os.path.join(OUT, f"{name}_chi2_qq.png"))
    return levels, res_m, res_q, counts, res_n, mc


def main(quick=False):
    runs = 64 if quick else 256
    names = [n for n in CASES if n in jc.robots.available()]
    print(f"robots: {names}; runs per Monte Carlo {runs}")
    print(f"{'robot':<10}{'params':>7}{'compile s':>10}{'vmap id/s':>10}{'loop id/s':>10}{'ratio':>7}{'2-dev id/s':>11}")
    for name in names:
        mc, loop_rate = speed(name, runs)
        rate = runs / mc.timings["run_s"]
        try:
            rate2 = two_devices(name, runs)
        except Exception as exc:  # noqa: BLE001  (report, do not hide)
            rate2 = float("nan")
            print(f"  two-device run failed: {exc}")
        print(f"{name:<10}{len(mc.names):>7}{mc.timings['compile_s']:>10.1f}{rate:>10.1f}{loop_rate:>10.1f}"
              f"{rate / loop_rate:>7.1f}{rate2:>11.1f}")
    print(f"peak memory (max RSS) {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    for name in names:
        levels, res_m, res_q, counts, res_n, mc = studies(name, 32 if quick else 64, quick)
        summ = mc.summary()
        print(f"\n{name}: residual norm vs measurement noise {dict(zip(levels, np.round(res_m, 8)))}")
        print(f"{name}: residual norm vs actuator noise {dict(zip(levels, np.round(res_q, 8)))}")
        print(f"{name}: model position error (m) vs number of measurements {dict(zip(counts, np.round(res_n, 9)))}")
        print(f"{name}: similarity(linear, MC) = {summ['similarity']:.3f}; inside 95% ellipsoid {summ['inside_95']:.3f} "
              f"(radius {summ['radius_95']:.2f}, radius holding 95% {summ['radius_holding_95']:.2f}); "
              f"Q-Q correlation {summ['qq_correlation']:.4f}")
        print(mc.table())


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    main(ap.parse_args().quick)
