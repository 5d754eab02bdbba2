"""Seed 004 pieces of issue 16 item 6: Clavel's direct solution of the Delta and K_crit (eq 2.118-2.134),
the open-loop Jacobian check of §2.4.3 (210 x 124), the theodolite + laser range device (§4.4.2), and
Table 3.2 (function and gradient evaluations of non-linear minimisation algorithms) with jaxcal's solvers.

    .venv/bin/python benchmarks/seed004_extras.py      # writes benchmarks/results/seed004_extras.json
"""

from __future__ import annotations

import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import jaxcal as jc  # noqa: E402
from jaxcal.closure import clavel as cl  # noqa: E402
from jaxcal.closure import delta as dl  # noqa: E402
from jaxcal.closure.core import closure_residual  # noqa: E402
from jaxcal.fit.identify import residual_weights, residuals  # noqa: E402
from jaxcal.kin.model import joint_variables  # noqa: E402

OUT = os.path.join(os.path.dirname(__file__), "results", "seed004_extras.json")


def central(f, x, h):
    x = np.asarray(x, float)
    return np.stack([(np.asarray(f(x + h * e)) - np.asarray(f(x - h * e))) / (2 * h) for e in np.eye(x.size)], axis=1)


def forward_diff(f, x, h):
    x = np.asarray(x, float)
    f0 = np.asarray(f(x))
    return np.stack([(np.asarray(f(x + h * e)) - f0) / h for e in np.eye(x.size)], axis=1)


def clavel_study(rb):
    """Clavel vs the general closure, its derivative, K_crit,1 and the loss of accuracy as h2 -> 0."""
    a = dl.full_precision_nominal(rb)
    theta = jnp.asarray(np.random.default_rng(0).uniform(-0.2, 1.4, (500, 3)))
    P_closure = jc.forward(rb, a, theta).p
    P_clavel, ok = jax.vmap(cl.direct)(theta)
    rel = []
    for t in np.asarray(theta[:20]):
        J = np.asarray(jax.jacfwd(lambda x: cl.direct(x)[0])(jnp.asarray(t)))
        F = central(lambda x: cl.direct(jnp.asarray(x))[0], t, 1e-6)
        rel.append(np.linalg.norm(J - F) / np.linalg.norm(F))
    K = cl.design_ratio()
    kmax = {}
    for label, lo, hi in [("full turn [-pi, pi]", -np.pi, np.pi), ("joint limits [-0.2, 1.4]", -0.2, 1.4)]:
        _, k = jax.vmap(cl.k_crit)(jnp.asarray(cl.actuator_box(lo, hi, 41)))
        kmax[label] = {"grid_41^3": float(jnp.max(k)), "closed_form": cl.k_crit_max_bound(lo, hi)}
    t1 = np.arccos(-(K + np.cos(1.4)) / 2 - K)
    deltas = [1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-12, 0.0]
    near = jnp.asarray([[t1 + d, 1.4, 1.4] for d in deltas] + [[t1 - d, 1.4, 1.4] for d in deltas[:-1]])
    ref = jc.forward(rb, a, near).p
    h2 = jax.vmap(lambda t: cl.h_terms(*cl.sphere_coefficients(t))[1])(near)
    err = jnp.max(jnp.abs(jax.vmap(cl.direct)(near)[0] - ref), axis=1)
    err_var = jnp.max(jnp.abs(jax.vmap(dl.direct)(near)[0] - ref), axis=1)
    box = jnp.asarray(cl.actuator_box(-np.pi, np.pi, 41))
    h2_nominal = jax.vmap(lambda t: cl.h2_of_ratio(t, K))(box)
    h2_wide = jax.vmap(lambda t: cl.h2_of_ratio(t, 1.2))(box)
    return {
        "max_abs_clavel_minus_general_closure_m": float(jnp.max(jnp.abs(P_clavel - P_closure))),
        "settings": int(theta.shape[0]), "all_feasible": bool(jnp.all(ok)),
        "jacfwd_vs_central_rel_err_max": float(max(rel)),
        "K_r_table_4_6": K, "K_crit_1": kmax,
        "h2_over_n2_full_turn_K_r": [float(jnp.min(h2_nominal)), float(jnp.max(h2_nominal))],
        "h2_over_n2_full_turn_K_1.2": [float(jnp.min(h2_wide)), float(jnp.max(h2_wide))],
        "near_h2_zero": {"theta1_star_deg": float(np.degrees(t1)), "theta2=theta3_rad": 1.4,
                         "rows": [{"delta": float(d), "h2": float(h), "clavel_err_m": float(e), "variation_err_m": float(v)}
                                  for d, h, e, v in zip([*deltas, *[-d for d in deltas[:-1]]], h2, err, err_var)]},
    }


def open_loop_study(rb):
    """§2.4.3: 30 frames x (position + Euler parameters) against the 124 geometric parameters."""
    a = rb.nominal
    cols = dl.open_loop_columns(rb)

    def jac_at(q, theta_free):
        qj = joint_variables(rb, a, q)
        vec = jax.jit(lambda x: dl.open_loop_vector(rb, x, qj, theta_free))
        J = np.asarray(jax.jit(jax.jacfwd(lambda x: dl.open_loop_vector(rb, x, qj, theta_free)))(a))
        return J, vec

    J, vec = jac_at(jnp.asarray(rb.home_np), jnp.asarray(rb.closure.start))

    def vec_cols(x):
        full = np.array(a)
        full[cols] = x
        return np.asarray(vec(jnp.asarray(full)))

    x0 = np.asarray(a)[cols]
    Jc = J[:, cols]
    diffs = {"central h=1e-6": float(np.max(np.abs(Jc - central(vec_cols, x0, 1e-6))))}
    for h in (1e-6, 1e-5, 4e-5, 1e-4):
        diffs[f"forward h={h:g}"] = float(np.max(np.abs(Jc - forward_diff(vec_cols, x0, h))))
    s = np.linalg.svd(Jc, compute_uv=False)
    s_all = np.linalg.svd(J, compute_uv=False)
    theta_grid, _ = jax.vmap(dl.inverse)(jnp.asarray(dl.grid()))
    sol = dl.solve(rb, a, theta_grid)
    conds = []
    for q, th in zip(np.asarray(theta_grid), np.asarray(sol.theta_free)):
        qj = joint_variables(rb, a, jnp.asarray(q))
        Jq = np.asarray(jax.jacfwd(lambda x: dl.open_loop_vector(rb, x, qj, jnp.asarray(th)))(a))[:, cols]
        sq = np.linalg.svd(Jq, compute_uv=False)
        conds.append(sq[0] / sq[-1])
    return {"shape": list(Jc.shape), "rank": int(np.sum(s > s[0] * 1e-12)), "condition_home": float(s[0] / s[-1]),
            "condition_125_grid_settings_min_median_max": [float(np.min(conds)), float(np.median(conds)), float(np.max(conds))],
            "all_157_columns_rank": int(np.sum(s_all > s_all[0] * 1e-12)), "autodiff_minus_fd_max": diffs,
            "thesis": {"shape": [210, 124], "fd_difference": 2e-5, "condition": 101}}


def device_study():
    """Combined theodolite + range on the Stanford arm: gradient, and what each device kind identifies."""
    rb = jc.robots.get("stanford")
    d_true = np.array([1.5, -0.4, 0.3, 0.05, -0.1, 2.2, 0.01, 0.02, 0.05])
    dev = jc.make_device("theodolite_range")
    q6 = jnp.asarray(jc.random_configurations(rb, 6, seed=1, margin=0.2))
    a_full = jnp.concatenate([jc.perturb(rb, 1e-3, seed=2), jnp.asarray(d_true)])
    y = jax.vmap(dev.read, (0, None))(jc.forward(rb, a_full[: rb.n_params], q6), jnp.asarray(d_true)) + 1e-3
    w = residual_weights(dev, 1.0, 1.0)
    f = lambda x: residuals(rb, dev, x, q6, y, w).ravel()  # noqa: E731
    J = np.asarray(jax.jacfwd(f)(a_full))
    F = central(f, np.asarray(a_full), 1e-6)
    out = {"gradient_rel_err_h1e-6": float(np.linalg.norm(J - F) / np.linalg.norm(F))}
    q = jc.random_configurations(rb, 60, seed=3, margin=0.2)
    a_true = jc.perturb(rb, 1e-3, seed=4)
    noise = {"position": 1e-4, "orientation": 1e-5}
    for kind, params in [("theodolite", d_true), ("laser_range", np.r_[d_true[:3], d_true[6:]]), ("theodolite_range", d_true)]:
        data = jc.simulate(rb, a_true, q, kind, device_params=params, noise=noise, seed=6)
        t = time.perf_counter()
        fit = jc.identify(rb, data, sigma_position=1e-4, sigma_orientation=1e-5)
        out[kind] = {"estimated": len(fit.estimated), "undetermined": len(fit.undetermined), "rms_after": fit.rms_after,
                     "sigma_hat": fit.sigma, "seconds_first_call": time.perf_counter() - t}
    return out


# -- Table 3.2 ---------------------------------------------------------------------------------
class Counter:
    """Counts executed evaluations of f: value only (the primal rule) and value with derivative (the JVP rule,
    which every linearisation and gradient goes through), by host callbacks that run inside compiled loops."""

    def __init__(self, f):
        self.value_only = self.with_derivative = 0

        def bump_value(_):
            self.value_only += 1

        def bump_derivative(_):
            self.with_derivative += 1

        @jax.custom_jvp
        def g(x):
            jax.debug.callback(bump_value, x[0])
            return f(x)

        @g.defjvp
        def g_jvp(primals, tangents):
            (x,), (dx,) = primals, tangents
            jax.debug.callback(bump_derivative, x[0])
            return jax.jvp(f, (x,), (dx,))

        self.f = g


LSQ = {"Gauss-Newton": lambda: optx.GaussNewton(rtol=1e-10, atol=1e-12),
       "Levenberg-Marquardt": lambda: optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
       "Dogleg": lambda: optx.Dogleg(rtol=1e-10, atol=1e-12)}
MIN = {"BFGS": lambda: optx.BFGS(rtol=1e-10, atol=1e-12)}


def count_solvers(residual, x0, max_steps=256):
    """Per solver: executed evaluations (value only / value with derivative), steps, final |r| (one problem,
    from x0). Least-squares solvers get r; BFGS minimises |r|^2 / 2 (its gradient, one reverse pass, goes
    through the JVP rule too). A solver that fails to run is recorded with its error."""
    out = {}
    for name, make in {**LSQ, **MIN}.items():
        c = Counter(residual)
        try:
            if name in LSQ:
                sol = optx.least_squares(lambda x, _: c.f(x), make(), x0, max_steps=max_steps, throw=False)
            else:
                sol = optx.minimise(lambda x, _: 0.5 * jnp.sum(c.f(x) ** 2), make(), x0, max_steps=max_steps, throw=False)
            jax.block_until_ready(sol.value)
        except Exception as exc:  # noqa: BLE001  (recorded: reverse mode through the generic closure)
            out[name] = {"error": f"{type(exc).__name__}: {str(exc)[:200]}"}
            continue
        ok = sol.result == optx.RESULTS.successful
        out[name] = {"value_only": c.value_only, "value_and_derivative": c.with_derivative,
                     "steps": int(sol.stats["num_steps"]), "converged": bool(ok),
                     "final_norm": float(jnp.linalg.norm(residual(sol.value)))}
    return out


def table_3_2(rb):
    """The three problems of Table 3.2 with jaxcal's optimistix solvers."""
    a = rb.nominal
    # closure: the Delta's 15 free joints at a grid setting from the closed home configuration
    theta_grid, _ = jax.vmap(dl.inverse)(jnp.asarray(dl.grid()))
    qj = joint_variables(rb, a, theta_grid[0])
    closure = count_solvers(lambda x: closure_residual(rb, a, qj, x), jnp.asarray(rb.closure.start))
    # implementation: actuator angles placing the nacelle at a grid target, nominal inverse of a neighbour as start
    target = jnp.asarray(dl.grid()[62])
    start = dl.inverse(target + jnp.array([0.05, -0.05, 0.05]))[0]
    a_long = a.at[rb.index("j26.d1")].add(0.02)
    implementation = count_solvers(lambda q: jc.forward(rb, a_long, q).p - target, start)
    # identification: the 3-D four-bar chain (6 frames, as the thesis' "4 bar chain with 6 frames"), 40 noise-free
    # positions, its base set (from `identify`) estimated from the nominal values by each solver
    fb = jc.robots.get("fourbar3d")
    q = jnp.asarray(jc.random_configurations(fb, 40, seed=1))
    dev = jc.make_device("position")
    data = jc.simulate(fb, jc.perturb(fb, 1e-3, seed=2), q, dev)
    fit = jc.identify(fb, data, known=("dev", "tool"))
    idx = np.array([fb.index(n) for n in fit.estimated])
    w = residual_weights(dev, 1e-3, 1e-3)
    y = jnp.asarray(data.y)

    def ident_residual(x):
        a_full = jnp.concatenate([fb.nominal.at[idx].set(x), dev.nominal])
        return residuals(fb, dev, a_full, q, y, w).ravel()

    ident = count_solvers(ident_residual, fb.nominal[idx])
    ident["identify_lm"] = {"estimated": len(fit.estimated), "rms_after_mm": fit.rms_after, "iterations": fit.iterations}
    thesis = {"closure": {"Gauss-Newton (leastsq)": [45, 14], "BFGS (bfgs.m)": [66, 67], "LM (levmrq.m)": [9, 9],
                          "LM (leastsq)": [52, 15]},
              "identification": {"Gauss-Newton": "failed", "BFGS (bfgs.m)": [162, 77], "Quasi-Newton (fminu.m)": [188, 39],
                                 "LM (leastsq)": "failed"},
              "implementation": {"Gauss-Newton": [7, 3], "BFGS (bfgs.m)": [13, 10], "Quasi-Newton (fminu.m)": [9, 3],
                                 "LM (leastsq)": [7, 3]}}
    return {"closure": closure, "implementation": implementation, "identification_fourbar3d": ident,
            "thesis_fn_grad": thesis}


def main():
    t0 = time.perf_counter()
    rb = jc.robots.get("delta")
    parts = sys.argv[1:] or ["clavel", "open_loop", "device", "table_3_2"]
    out = json.load(open(OUT)) if os.path.exists(OUT) else {}
    for part in parts:
        t = time.perf_counter()
        out[part] = {"clavel": lambda: clavel_study(rb), "open_loop": lambda: open_loop_study(rb), "device": device_study,
                     "table_3_2": lambda: table_3_2(rb)}[part]()
        out[part]["seconds"] = time.perf_counter() - t
        print(part, json.dumps(out[part], indent=1, default=float))
    out["machine"] = "shared 2-core CPU (OPENBLAS_NUM_THREADS=1), float64"
    out["total_seconds_last_run"] = time.perf_counter() - t0
    with open(OUT, "w") as fh:
        json.dump(out, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
