"""Delta closure and calibration speed (seed 004 §4.3-4.4), one process, compile time apart.

1. Delta closures per second through `jc.forward` (nominal direct solution start + Newton on the
   reduced square system, kept on the nominal branch; the continuation of `jaxcal.closure.track`
   for the other samples: `jaxcal.closure.delta`), vmapped over 125 and 10,000 actuator settings
   (nominal, and with 1 cm errors on the free parameters), against the generic closure of
   `jaxcal.closure` (same robot, same settings, continued from the closed home setting) and
   against the thesis' ~10 s per closure in MATLAB.
2. One full Delta identification (simulation 1: 125 full-pose readings of the 400 mm grid, rod 26
   20 mm longer, 74 free parameters, base set, LM): compile and run apart.
3. Compensation on the 125-point grid: worst tool position error before (nominal inverse solution
   commanded) and after (calibrated model compensated), time per point.

Run: python benchmarks/closure.py   (writes benchmarks/results/closure.json)
"""

from __future__ import annotations

import json
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import median_time

import jaxcal as jc
from jaxcal.closure import delta as dl
from jaxcal.fit.compensate import compensate

THESIS_SECONDS_PER_CLOSURE = 10.0  # seed 004 §5: ~10 s per Delta direct solution (closure) in MATLAB


def settings(n, seed=0):
    """n actuator settings whose nacelle centre lies in the 400 mm grid cube."""
    P = dl.grid()[0] + 0.4 * np.random.default_rng(seed).random((n, 3))
    return jax.jit(jax.vmap(dl.inverse))(jnp.asarray(P))[0]


def timed_first(fn):
    t = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t


def closure_rates(rb):
    out = {}
    for n in (125, 10_000):
        q = settings(n)
        fast = lambda q=q: jc.forward(rb, rb.nominal, q).p  # noqa: E731
        first = timed_first(fast)
        t = median_time(lambda: jax.block_until_ready(fast()), repeat=5)
        ok = bool(jnp.all(dl.closed(rb, rb.nominal, q)))
        out[n] = {"fast_first_call_s": first, "fast_s": t, "fast_per_s": n / t, "all_closed": ok,
                  "ratio_vs_thesis": THESIS_SECONDS_PER_CLOSURE / (t / n)}
        print(f"Delta closure, {n:>6} settings: first call {first:.2f} s, then {t * 1e3:.2f} ms "
              f"= {n / t:,.0f} closures/s (all closed: {ok}); thesis 10 s/closure -> x{THESIS_SECONDS_PER_CLOSURE / (t / n):.2e}")
    # 1 cm / 0.01 rad errors on the free parameters: samples the fast Newton does not close on the nominal branch
    # go through the general path (continuation, `jaxcal.closure.track`); the batch pays for the slowest sample
    a = jc.perturb(rb, 1e-2, seed=1)
    q = settings(10_000)
    fast = lambda: jc.forward(rb, a, q).p  # noqa: E731
    first = timed_first(fast)
    t = median_time(lambda: jax.block_until_ready(fast()), repeat=5)
    status = np.asarray(dl.solve(rb, a, q).status)
    out["perturbed_1cm_10000"] = {"first_call_s": first, "s": t, "per_s": 10_000 / t,
                                  "status_counts": np.bincount(status, minlength=3).tolist()}
    print(f"Delta closure, 1 cm errors, 10,000 settings: {t * 1e3:.1f} ms = {10_000 / t:,.0f} closures/s; "
          f"status closed/unclosed/other mode {np.bincount(status, minlength=3).tolist()}")
    try:  # the generic closure of jaxcal.closure on the same robot, for the ratio
        from jaxcal.closure import solve

        q = settings(125)
        generic = lambda: solve(rb, rb.nominal, q).theta_free  # noqa: E731
        first = timed_first(generic)
        t = median_time(lambda: jax.block_until_ready(generic()), repeat=3)
        agree = float(jnp.max(jnp.abs(solve(rb, rb.nominal, q).theta_free - dl.solve(rb, rb.nominal, q).theta_free)))
        out["generic_125"] = {"first_call_s": first, "s": t, "per_s": 125 / t, "max_joint_difference": agree,
                              "fast_speedup": out[125]["fast_per_s"] / (125 / t)}
        print(f"generic LM closure, 125 settings: first call {first:.2f} s, then {t * 1e3:.1f} ms = {125 / t:,.0f}/s; "
              f"fast path x{out['generic_125']['fast_speedup']:.1f}; joint values agree to {agree:.1e} rad")
    except Exception as exc:  # report, do not hide: the generic solver may not handle this robot yet
        out["generic_125"] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
        print(f"generic LM closure failed: {out['generic_125']['error']}")
    return out


def identification(rb):
    q = np.asarray(jax.jit(jax.vmap(dl.inverse))(jnp.asarray(dl.grid()))[0])
    a_true = rb.nominal.at[rb.index("j26.d1")].add(0.02)
    data = jc.simulate(rb, a_true, q, "pose")
    t = time.perf_counter()
    fit = jc.identify(rb, data, known=("dev", "tool"))
    first = time.perf_counter() - t
    runs = []
    for _ in range(3):
        t = time.perf_counter()
        again = jc.identify(rb, data, known=("dev", "tool"))
        runs.append((time.perf_counter() - t, again.timings["run_s"]))
    wall, solve_s = np.median([r[0] for r in runs]), np.median([r[1] for r in runs])
    err = float(fit.a[rb.index("j26.d1")] - a_true[rb.index("j26.d1")])
    print(f"Delta identification (125 poses, {len(fit.estimated)} estimated): first call {first:.1f} s "
          f"(compile {fit.timings['compile_s']:.1f} s), then {wall:.2f} s per identify call, LM solve {solve_s:.2f} s, "
          f"{fit.iterations} iterations; d1_26 error {err:.1e} m; RMS {fit.rms_before:.3g} -> {fit.rms_after:.2e} mm")
    return {"first_call_s": first, "compile_s": fit.timings["compile_s"], "identify_wall_s": float(wall),
            "lm_solve_s": float(solve_s), "iterations": fit.iterations, "d1_26_error_m": err,
            "rms_before_mm": fit.rms_before, "rms_after_mm": fit.rms_after, "a": np.asarray(fit.a).tolist()}


def compensation(rb, a_cal):
    a_true = rb.nominal.at[rb.index("j26.d1")].add(0.02)
    P = jnp.asarray(dl.grid())
    q_nom = jax.jit(jax.vmap(dl.inverse))(P)[0]
    before = jnp.linalg.norm(jc.forward(rb, a_true, q_nom).p - P, axis=-1)
    first = timed_first(lambda: compensate(rb, a_cal, P, start=q_nom).q)
    t = median_time(lambda: jax.block_until_ready(compensate(rb, a_cal, P, start=q_nom).q), repeat=5)
    comp = compensate(rb, a_cal, P, start=q_nom)
    after = jnp.linalg.norm(jc.forward(rb, a_true, comp.q).p - P, axis=-1)
    print(f"compensation, 125 grid points: worst error {float(jnp.max(before)) * 1e3:.3f} mm -> {float(jnp.max(after)) * 1e3:.2e} mm; "
          f"first call {first:.2f} s, then {t / 125 * 1e6:.1f} us per point (thesis: 6-20 s per point)")
    return {"worst_before_mm": float(jnp.max(before)) * 1e3, "worst_after_mm": float(jnp.max(after)) * 1e3,
            "first_call_s": first, "per_point_s": t / 125}


def write_json(result, path):
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".json.tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(result, fh, indent=1)
    os.replace(tmp, path)


def main():
    rb = jc.robots.get("delta")
    result = {"device": jax.devices()[0].device_kind, "closure": closure_rates(rb)}
    result["identification"] = identification(rb)
    a_cal = jnp.asarray(result["identification"].pop("a"))
    result["compensation"] = compensation(rb, a_cal)
    write_json(result, os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "closure.json"))


if __name__ == "__main__":
    main()
