"""The 3-D four-bar Monte Carlo study of seed 004 §4.3.1 (Table 4.2, Figures 4.12-4.14 and 4.19, Table 4.3).

The robot is `jc.robots.get("fourbar3d")` (Table 4.2a); the true robot is the Table 4.2b perturbation
restricted to the base set that full-pose measurements of frame 5 identify (the other Table 4.2b
entries are absorbed by the regrouping and would leave a deterministic model error). Every data set
is `N_POSES` full poses of frame 5 at random crank angles; the device frame and the tool are known.

Table 4.2c gives *variances*: the covariances are Sigma_m = Wc s_m and Sigma_theta = Wc s_theta with
Wc = I, so the noise standard deviations are sqrt(s_m) (metres and radians alike) and sqrt(s_theta)
(radians of the crank). The ten (s_m, s_theta) runs are the points of Figure 4.12; run 3 is the one
the thesis analyses in Table 4.3 and Figure 4.19. The residual is the plain 2-norm of eq 4.1 over all
pose components (Wc = I: metres and radians added as they are).

Each point is `jaxcal.uncertainty.monte_carlo`: one vmapped, compiled Gauss-Newton identification per
noise draw (through the loop closure, whose derivative comes from the implicit function theorem).
Outputs (atomic writes): benchmarks/results/montecarlo_fourbar3d.json and montecarlo_fourbar3d_*.png.

Run: python benchmarks/montecarlo_fourbar3d.py [--quick] [--speed]

`--thesis-conditions [--draws N]` runs run 3 under the thesis' own conditions instead (issue 16 item 5):
the 14-parameter base set or the thesis' 26 parameters (the Table 4.2b entries that differ from nominal,
alpha_2,2 = j2.a2 among them, estimated without the base-set reduction), each started from the
noise-free estimate or from the nominal model (LM). Output: benchmarks/results/montecarlo_fourbar3d_thesis_conditions.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

import jaxcal as jc
from jaxcal.fit import core
from jaxcal.fit import uncertainty as un
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.io_atomic import write_json_atomic
from jaxcal.robots.builtin import FOURBAR3D_TABLE_4_2B

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
N_POSES = 30
CHUNK = 32  # one compiled Monte Carlo kernel for every point with N_POSES poses

# Table 4.2c: (s_m, s_theta) variances of the ten runs. The OCR lost the mantissa of runs 4 and 9
# ("x10-9"); 1e-9 is taken.
TABLE_4_2C = [(1e-4, 0.0), (2.5e-6, 0.0), (2.5e-8, 0.0), (1e-9, 0.0), (2.5e-11, 0.0),
              (1e-4, 1e-6), (2.5e-6, 1e-6), (2.5e-8, 1e-6), (1e-9, 1e-6), (2.5e-11, 1e-6)]
THESIS = {  # the numbers seed 004 §4.3.1 prints for run 3 (26 parameters, one of them redundant)
    "similarity": 0.35, "inside_95": 0.86, "radius_95": 6.2, "radius_holding_95": 7.1, "parameters": 26,
    "crossover_measurement_var_at_actuator_1e-6": 1e-7, "crossover_actuator_var_at_measurement_2.5e-7": 1e-7,
    # Table 4.3 columns 3 and 4: eigenvalues of the linear and of the Monte Carlo covariance (non-zero ones)
    "eig_linear": [4.25e-5, 3.47e-5, 1.89e-5, 5e-7, 2.25e-7, 2.22e-7, 1.73e-7, 1.04e-7, 9.76e-8, 5.9e-8, 4.98e-8,
                   2.13e-8, 1.64e-8, 1.11e-8, 7.32e-9, 2.68e-9, 1.2e-9, 7.9e-10, 6.63e-10],
    "eig_mc": [3.97e-5, 3.67e-5, 1.78e-5, 1.38e-5, 1.92e-6, 6.07e-7, 2.58e-7, 1.67e-7, 1.59e-7, 1.19e-7, 9.62e-8,
               7.49e-8, 5.32e-8, 4.47e-8, 1.52e-8, 1.14e-8, 8.18e-9, 4.99e-9, 2.85e-9, 1.91e-9, 1.34e-9, 5.12e-10],
}


def table_4_2b(rb):
    """Table 4.2b as a parameter vector of `rb` (entries named j<body>.<field>)."""
    vals = {f"j{i}.{f}": v for i, row in enumerate(FOURBAR3D_TABLE_4_2B, 1) for f, v in zip(("a1", "a2", "a3", "d1", "d2", "d3"), row)}
    return np.array([vals[n] for n in rb.names])


def start_base_set(rb, data) -> np.ndarray:
    """Indices of the robot parameters `identify(rb, data, known=("dev", "tool"))` estimates: the base set at its
    start (the nominal model, device and tool known), from the calibration core's own rule without the solve."""
    dev = data.device
    known = np.array([n.split(".")[0] in ("dev", "tool") for n in dev.names])
    problem = core.make_problem(rb, dev, data.q, data.y, weights=residual_weights(dev),
                                free=np.concatenate([rb.free_mask, dev.free_mask & ~known]),
                                a_ref=np.concatenate([rb.nominal, dev.nominal]))
    return core.choose_estimated(problem, problem.jacobian(problem.a_ref), True, None)[0]


def setup(n_poses=N_POSES, seed=2):
    """(robot, true parameters, crank angles): Table 4.2b on the base set of a pose identification."""
    rb = jc.robots.get("fourbar3d")
    q = jc.random_configurations(rb, n_poses, seed=seed, margin=0.05)
    est = start_base_set(rb, jc.simulate(rb, rb.nominal, q, "pose"))
    a_true = np.array(rb.nominal)
    a_true[est] = table_4_2b(rb)[est]
    return rb, a_true, q


def run_point(rb, a_true, q, var_m, var_q, runs, seed=0, chunk=CHUNK):
    """Monte Carlo at one (s_m, s_theta) variance pair. The solver weights are 1/sigma with one sigma for
    position and orientation (Wc = I), so the weighted residual norm times sigma is the plain norm."""
    sd_m, sd_q = float(np.sqrt(var_m)), float(np.sqrt(var_q))
    sigma = sd_m if sd_m > 0 else max(sd_q, 1e-12)
    mc = un.monte_carlo(rb, a_true, q, "pose", noise={"position": sd_m, "orientation": sd_m, "actuator": sd_q},
                        runs=runs, known=("dev", "tool"), seed=seed, chunk=chunk, devices=[],
                        sigma_position=sigma, sigma_orientation=sigma)
    return mc, mc.residual_norms * sigma


def residual_before(rb, a_true, q):
    """Plain 2-norm of eq 4.1 for the nominal model on the noise-free data (the 'before' line)."""
    data = jc.simulate(rb, a_true, q, "pose")
    dev = data.device
    x = jnp.concatenate([rb.nominal, dev.nominal])
    r = residuals(rb, dev, x, jnp.asarray(data.q), jnp.asarray(data.y), residual_weights(dev, 1.0, 1.0))
    return float(jnp.linalg.norm(r))


def crossover(levels, alone, floor):
    """Equal-contribution point: the variance at which the residual of one noise source alone reaches
    `floor`, the residual of the other source alone (log-log interpolation); None outside the levels."""
    lv, a, f = np.log(levels), np.log(np.asarray(alone)), np.log(floor)
    for i in range(len(lv) - 1):
        if a[i] <= f <= a[i + 1]:
            return float(np.exp(lv[i] + (lv[i + 1] - lv[i]) * (f - a[i]) / (a[i + 1] - a[i])))
    return None


def table_runs(rb, a_true, q, runs, runs_run3):
    """The ten runs of Table 4.2c; run 3 with more draws (Table 4.3, Figure 4.19)."""
    out, mc3 = [], None
    for k, (vm, vq) in enumerate(TABLE_4_2C, 1):
        t = time.perf_counter()
        mc, norms = run_point(rb, a_true, q, vm, vq, runs_run3 if k == 3 else runs, seed=k)
        s = mc.summary()
        row = {"run": k, "var_m": vm, "var_theta": vq, "draws": len(norms), "residual_median": float(np.median(norms)),
               "residual_expected": float(np.sqrt(6 * len(q) - len(mc.names)) * np.sqrt(vm)) if vq == 0 else None,
               **{key: s[key] for key in ("converged", "outliers", "similarity", "inside_95", "radius_95",
                                          "radius_holding_95", "qq_correlation", "bias_over_std")},
               "max_iterations": int(mc.iterations.max()), "wall_s": time.perf_counter() - t}
        out.append(row)
        print(f"run {k:>2}  s_m {vm:8.1e}  s_theta {vq:7.1e}  draws {len(norms):>4}  residual {row['residual_median']:.3e}  "
              f"similarity {s['similarity']:.3f}  inside95 {s['inside_95']:.3f}  r95 {s['radius_95']:.2f}/"
              f"{s['radius_holding_95']:.2f}  Q-Q {s['qq_correlation']:.4f}  outliers {s['outliers']}  {row['wall_s']:.0f} s",
              flush=True)
        if k == 3:
            mc3 = mc
    return out, mc3


def actuator_sweep(rb, a_true, q, runs, levels):
    """Figure 4.13: residual norm vs actuator noise, traces s_m = 0 and s_m = 2.5e-7."""
    traces = {}
    for vm in (0.0, 2.5e-7):
        traces[vm] = [float(np.median(run_point(rb, a_true, q, vm, vq, runs, seed=50 + i)[1])) for i, vq in enumerate(levels)]
        print(f"Figure 4.13, s_m = {vm:g}: " + ", ".join(f"{v:.3e}" for v in traces[vm]), flush=True)
    return traces


def count_sweep(rb, a_true, counts, runs, var_m=2.5e-8, n_test=50):
    """Figure 4.14: error of the identified model on held-out poses vs number of measurements, noise-free
    (the noise-free identification) and with run 3's measurement noise (median over the draws)."""
    q_test = jnp.asarray(jc.random_configurations(rb, n_test, seed=9, margin=0.05))
    true = jc.forward(rb, jnp.asarray(a_true), q_test)
    tool = jax.jit(lambda a: jc.forward(rb, a, q_test))

    def pose_error(a):
        p = tool(jnp.asarray(a))
        dp = np.sum((np.asarray(p.p) - np.asarray(true.p)) ** 2, -1)
        dR = np.sum((np.asarray(p.R) - np.asarray(true.R)) ** 2, (-1, -2)) / 2  # ~ |rotation error|^2
        return float(np.sqrt(np.mean(dp + dR)))

    clean, noisy = [], []
    for k in counts:
        qk = jc.random_configurations(rb, k, seed=3, margin=0.05)
        mc, _ = run_point(rb, a_true, qk, var_m, 0.0, runs, seed=200 + k, chunk=runs)
        idx = [rb.index(n) for n in mc.names]
        base = np.array(rb.nominal)  # the noise-free identification: nominal off the base set
        base[idx] = mc.reference
        clean.append(pose_error(base))
        errs = []
        for row in mc.estimates[mc.converged]:
            a_est = base.copy()
            a_est[idx] = row
            errs.append(pose_error(a_est))
        noisy.append(float(np.median(errs)))
        print(f"Figure 4.14, {k:>3} poses ({len(mc.names)} estimated): model error noise-free {clean[-1]:.3e}, "
              f"noisy {noisy[-1]:.3e}", flush=True)
    return clean, noisy


def sampling_similarity(cov, n, reps=200, seed=0):
    """The similarity (eq A.56) between `cov` and the sample covariance of n Gaussian draws with covariance
    `cov`: what sampling alone gives. Returns (median, 95th percentile) over `reps` repetitions."""
    rng = np.random.default_rng(seed)
    vals = [un.similarity(cov, np.cov(rng.multivariate_normal(np.zeros(len(cov)), cov, size=n).T)) for _ in range(reps)]
    return float(np.median(vals)), float(np.quantile(vals, 0.95))


def sensitivities(rb, a_true, q, mc, var_m, extent=1e-4, seed=7):
    """Table 4.3 column 6 / Figure 4.20: the rise of the weighted cost (eq 4.5) for one noisy data set
    when the estimate moves a common `extent` along each eigenvector of the Monte Carlo covariance.
    Returns (Monte Carlo eigenvalues, cost rises, log-log slope of rise vs eigenvalue; -1 is the
    inverse relation the thesis notes)."""
    sd = float(np.sqrt(var_m))
    data = jc.simulate(rb, a_true, q, "pose", noise={"position": sd, "orientation": sd}, seed=seed)
    fit = jc.identify(rb, data, known=("dev", "tool"), sigma_position=sd, sigma_orientation=sd)
    if tuple(fit.estimated) != tuple(mc.names):
        raise RuntimeError(f"noisy fit estimated {fit.estimated}, Monte Carlo {mc.names}")
    lam, _, rise = un.cost_sensitivity(fit, data, mc.covariance_mc, extent=extent)
    slope = float(np.polyfit(np.log(lam), np.log(rise), 1)[0])
    return lam, rise, slope


def table_4_3(mc):
    """Table 4.3 layout for run 3: diagonals, sorted eigenvalues, the eigenvector of the worst eigenvalue
    ratio, and the simultaneous 95 % confidence interval widths (eq 3.42) from the Monte Carlo covariance."""
    cl, cm = mc.covariance_linear, mc.covariance_mc
    el, em = np.sort(np.linalg.eigvalsh(cl))[::-1], np.sort(np.linalg.eigvalsh(cm))[::-1]
    worst = int(np.argmax(np.abs(np.log(em / el))))
    lam, V = np.linalg.eigh(cm)
    v = V[:, np.argsort(lam)[::-1][worst]]
    lo, hi = un.confidence_intervals(mc.estimates[mc.converged & mc.keep].mean(0), cm, simultaneous=True)
    return {"names": list(mc.names), "diag_linear": np.diag(cl), "diag_mc": np.diag(cm), "eig_linear": el, "eig_mc": em,
            "worst_eigenvalue": worst + 1, "worst_eigenvector": v, "worst_eigenvector_main": mc.names[int(np.argmax(np.abs(v)))],
            "ci_width_95_simultaneous": hi - lo}


def thesis_free(rb):
    """The thesis' 26 estimated parameters: the Table 4.2b entries that differ from nominal (a3 of bodies 2-6 is
    not perturbed and not estimated; j2.a2, the thesis' redundant alpha_2,2, is among them)."""
    return [n for n, a, b in zip(rb.names, np.asarray(rb.nominal), table_4_2b(rb)) if a != b]


def run_condition(rb, a_true, q, free, start, runs, var_m=TABLE_4_2C[2][0], seed=3, chunk=CHUNK, max_steps=50):
    """Run 3 Monte Carlo with the estimated set `free` (None: the base set) from `start` ("reference" or
    "nominal"). Gauss-Newton needs a regular normal matrix: a rank-deficient set (the 26) is solved by LM."""
    sd = float(np.sqrt(var_m))
    solver = "lm" if free is not None or start == "nominal" else None
    return un.monte_carlo(rb, a_true, q, "pose", noise={"position": sd, "orientation": sd}, runs=runs,
                          known=("dev", "tool"), seed=seed, chunk=chunk, devices=[], sigma_position=sd,
                          sigma_orientation=sd, solver=solver, start=start, max_steps=max_steps,
                          free=None if free is None else list(free), base=free is None)


def linear_covariance_svd(rb, a_true, q, mc, var_m=TABLE_4_2C[2][0], rtol=1e-10):
    """Linear covariance (eq 3.28, measurement noise only, Wc = I) of the estimated set at the noise-free estimate:
    sigma^2 (J^T J)^+ by the SVD of J with singular values below rtol times the largest cut. With Sigma_m = sigma^2 I
    and weights 1/sigma it equals `un.linear_covariance`, whose pinv of the formed J^T W J lets round-off eigenvalues
    (~1e-16 relative) of a rank-deficient set through as huge variances. Returns (covariance, rank of J)."""
    sd = float(np.sqrt(var_m))
    clean = jc.simulate(rb, a_true, q, "pose")
    dev = clean.device
    idx = np.array([rb.index(n) for n in mc.names])
    x = np.concatenate([np.asarray(rb.nominal), np.asarray(dev.nominal)])
    x[idx] = mc.reference
    J = np.asarray(core.jacobian(rb, dev, jnp.asarray(x), jnp.asarray(clean.q), jnp.asarray(clean.y),
                                 residual_weights(dev, sd, sd)))[:, idx]
    _, sv, Vt = np.linalg.svd(J, full_matrices=False)
    r = int(np.sum(sv > rtol * sv[0]))
    return (Vt[:r].T / sv[:r] ** 2) @ Vt[:r], r


def coverage(X, cov, dof):
    """Share of the rows of X inside the 95 % ellipsoid of `cov` about their mean, radius sqrt(chi2_dof(0.95)) (the
    thesis' eq 4.3 takes dof = 26, the number estimated), the distance through the pseudo-inverse (the null
    directions of a rank-deficient `cov` do not enter). Returns (share, radius, radius holding 95 %)."""
    d = X - X.mean(0)
    d2 = np.einsum("ij,jk,ik->i", d, np.linalg.pinv(cov, rcond=1e-12, hermitian=True), d)
    r2 = scipy.stats.chi2.ppf(0.95, dof)
    return float(np.mean(d2 <= r2)), float(np.sqrt(r2)), float(np.sqrt(np.quantile(d2, 0.95)))


def worst_eigenvalue(names, cov_lin, cov_mc, rank):
    """Among the `rank` leading sorted eigenvalues (those the linear analysis gives), the one with the largest
    MC/linear ratio: (1-based position, ratio, name of the largest entry of its MC eigenvector)."""
    el, (lam, V) = np.sort(np.linalg.eigvalsh(cov_lin))[::-1], np.linalg.eigh(cov_mc)
    order = np.argsort(lam)[::-1]
    ratio = lam[order][:rank] / el[:rank]
    k = int(np.argmax(ratio))
    return k + 1, float(ratio[k]), names[int(np.argmax(np.abs(V[:, order[k]])))]


def null_spread(names, cov_lin, cov_mc, rank):
    """Monte Carlo variance in the null space of the linear covariance (directions the data do not determine) and
    the parameter that carries most of it."""
    _, V = np.linalg.eigh(cov_lin)
    N = V[:, : len(V) - rank]
    per_param = np.diag(N @ (N.T @ cov_mc @ N) @ N.T)
    return float(per_param.sum()), names[int(np.argmax(per_param))] if rank < len(V) else None


def accepted_draws(mc, ratio=1.5, k=5.0):
    """Draws that reached the minimum (weighted residual norm within `ratio` of the median: LM's step test
    fails on a rank-deficient set while the cost is already minimal) and pass eq 4.2 (median + k MAD of the
    distance from the noise-free estimate). Returns (mask over draws, count failing the residual test)."""
    norms = np.where(np.isfinite(mc.residual_norms), mc.residual_norms, np.inf)
    reached = (norms <= ratio * np.median(norms)) & np.all(np.isfinite(mc.estimates), 1)
    keep = np.zeros(len(norms), bool)
    keep[np.flatnonzero(reached)] = un.reject_outliers(mc.estimates[reached], mc.reference, k)[0]
    return keep, int((~reached).sum())


def condition_row(mc, rb, a_true, q):
    """Table 4.3 / Figures 4.16-4.17 quantities of one condition."""
    keep, false_minima = accepted_draws(mc)
    X = mc.estimates[keep]
    cov_lin, rank = linear_covariance_svd(rb, a_true, q, mc)
    cov_mc = np.cov(X.T)
    inside, r95, r_emp = coverage(X, cov_lin, len(mc.names))
    inside_r, r95_r, _ = coverage(X, cov_lin, rank)
    pos, ratio, main = worst_eigenvalue(mc.names, cov_lin, cov_mc, rank)
    null_var, null_main = null_spread(mc.names, cov_lin, cov_mc, rank)
    nominal = np.asarray(rb.nominal)[[rb.index(n) for n in mc.names]]
    r_o = np.linalg.norm(mc.estimates - nominal, axis=1)  # eq 4.2 about the nominal model (Figure 4.17)
    far = r_o > np.median(r_o) + 5 * 1.4826 * np.median(np.abs(r_o - np.median(r_o)))
    inside_s, _, r_emp_s = coverage(X, cov_mc, len(mc.names))  # about the sample covariance, as a chi-square plot
    return {"estimated": len(mc.names), "linear_rank": rank, "draws": len(mc.estimates), "used": int(keep.sum()),
            "solver_converged": int(mc.converged.sum()), "false_minima": false_minima,
            "outliers_eq_4_2": int(len(keep) - keep.sum() - false_minima),
            "r_o_from_nominal_median": float(np.median(r_o)), "r_o_from_nominal_95": float(np.quantile(r_o, 0.95)),
            "r_o_from_nominal_max": float(r_o.max()), "far_from_nominal_5mad": int(far.sum()),
            "inside_95_sample_cov": inside_s, "radius_holding_95_sample_cov": r_emp_s, "qq_correlation": un.chi2_qq(X)[2],
            "similarity": un.similarity(cov_lin, cov_mc), "similarity_library_linear": un.similarity(mc.covariance_linear, cov_mc),
            "inside_95": inside, "radius_95": r95, "radius_holding_95": r_emp, "inside_95_dof_rank": inside_r,
            "radius_95_dof_rank": r95_r, "worst_eigenvalue": pos, "worst_ratio": ratio, "worst_eigenvector_main": main,
            "mc_variance_in_linear_null_space": null_var, "null_space_main": null_main,
            "eig_linear": np.sort(np.linalg.eigvalsh(cov_lin))[::-1][:rank], "eig_mc": np.sort(np.linalg.eigvalsh(cov_mc))[::-1],
            "sd_mc": dict(zip(mc.names, np.sqrt(np.diag(cov_mc)))), "sd_linear": dict(zip(mc.names, np.sqrt(np.diag(cov_lin)))),
            "iterations_median": float(np.median(mc.iterations)), "iterations_max": int(mc.iterations.max()),
            "solver": mc.timings["solver"], "compile_s": mc.timings["compile_s"], "run_s": mc.timings["run_s"]}


CONDITIONS = {"a_base14_truth": (False, "reference"), "b_thesis26_truth": (True, "reference"),
              "c_thesis26_nominal": (True, "nominal"), "d_base14_nominal": (False, "nominal")}


def thesis_conditions(runs, only=None, max_steps=50):
    """Run 3 under conditions (a)-(d) (`CONDITIONS`: thesis' 26 or the base set, from the truth or from nominal)
    with the same noise draws; writes montecarlo_fourbar3d_thesis_conditions.json after each condition (a solver
    budget other than the default 50 steps is stored under the condition's key + "_<max_steps>_steps")."""
    rb, a_true, q = setup()
    res = {"robot": "fourbar3d", "n_poses": len(q), "var_m": TABLE_4_2C[2][0], "var_theta": 0.0, "draws": runs,
           "thesis_26": thesis_free(rb), "thesis": {k: THESIS[k] for k in ("similarity", "inside_95", "radius_95",
                                                                          "radius_holding_95", "parameters")},
           "thesis_worst": {"eigenvalue": 4, "ratio": 27.6, "main": "alpha_2,2 (j2.a2)"}, "conditions": {}}
    path = os.path.join(OUT, "montecarlo_fourbar3d_thesis_conditions.json")
    if only and os.path.exists(path):  # a partial run adds to the conditions already there
        with open(path) as f:
            res["conditions"] = json.load(f).get("conditions", {})
    for key, (thesis26, start) in CONDITIONS.items():
        if only and key[0] not in only:
            continue
        t = time.perf_counter()
        mc = run_condition(rb, a_true, q, thesis_free(rb) if thesis26 else None, start, runs, max_steps=max_steps)
        row = {**condition_row(mc, rb, a_true, q), "wall_s": time.perf_counter() - t}
        key = key if max_steps == 50 else f"{key}_{max_steps}_steps"
        res["conditions"][key] = row
        print(f"{key:<20} {row['estimated']} est (rank {row['linear_rank']})  similarity {row['similarity']:.3f}  "
              f"inside95 {row['inside_95']:.3f} (sample {row['inside_95_sample_cov']:.3f})  "
              f"r95 {row['radius_95']:.2f}/{row['radius_holding_95']:.2f}  worst eig "
              f"#{row['worst_eigenvalue']} x{row['worst_ratio']:.2f} ({row['worst_eigenvector_main']})  null var "
              f"{row['mc_variance_in_linear_null_space']:.2e} ({row['null_space_main']})  used {row['used']}  "
              f"LM flag {row['solver_converged']}  outliers {row['outliers_eq_4_2']}  false minima {row['false_minima']}  "
              f"its {row['iterations_median']:.0f}/"
              f"{row['iterations_max']}  compile {row['compile_s']:.0f} s  total {row['wall_s']:.0f} s", flush=True)
        os.makedirs(OUT, exist_ok=True)
        write_json_atomic(path, res)
    return res


def plots(res, mc3, levels_m, levels_q):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxcal.report import save_atomic

    fig, axs = plt.subplots(1, 3, figsize=(14, 3.8))
    for vq, tr in res["figure_4_12"]["traces"].items():
        axs[0].loglog(levels_m, tr, "o-", label=f"actuator s_theta = {vq}")
    axs[0].axhline(res["residual_before"], color="k", ls=":", label="before (nominal model)")
    axs[0].set(xlabel="measurement noise variance s_m", ylabel="residual 2-norm after identification", title="cf. Figure 4.12")
    for vm, tr in res["figure_4_13"]["traces"].items():
        axs[1].loglog(levels_q, tr, "o-", label=f"measurement s_m = {vm}")
    axs[1].axhline(res["residual_before"], color="k", ls=":")
    axs[1].set(xlabel="actuator noise variance s_theta [rad^2]", title="cf. Figure 4.13")
    f14 = res["figure_4_14"]
    axs[2].semilogy(f14["counts"], np.maximum(f14["noise_free"], 1e-16), "o-", label="noise-free")
    axs[2].semilogy(f14["counts"], f14["noisy"], "s-", label=f"s_m = {f14['var_m']:g}")
    axs[2].set(xlabel="number of pose measurements", ylabel="model pose error on 50 held-out poses", title="cf. Figure 4.14")
    for ax in axs:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("fourbar3d (Table 4.2): Monte Carlo identifications through the loop closure")
    save_atomic(fig, os.path.join(OUT, "montecarlo_fourbar3d_residuals.png"))

    X = mc3.estimates[mc3.converged & mc3.keep]
    d2, quant, corr = un.chi2_qq(X)
    fig, ax = plt.subplots(figsize=(4.8, 4.4))
    rng = np.random.default_rng(0)
    for i in range(3):  # pseudo-random Gaussian sets with the same covariance, as the thesis plots beside its own
        G = rng.multivariate_normal(X.mean(0), np.cov(X.T), size=len(X))
        g2, gq, _ = un.chi2_qq(G)
        ax.plot(gq, g2, "-", color="0.7", lw=1, label="Gaussian, same covariance" if i == 0 else None)
    ax.plot(quant, d2, ".", ms=4, label="Monte Carlo run 3")
    ax.plot(quant, quant, "k-", lw=1)
    ax.set(xlabel=f"chi-square({X.shape[1]}) quantile", ylabel="sorted Mahalanobis d^2",
           title=f"cf. Figure 4.19 (r = {corr:.4f}, {len(X)} draws)")
    ax.legend(fontsize=7)
    save_atomic(fig, os.path.join(OUT, "montecarlo_fourbar3d_chi2_qq.png"))

    sens = res["run3"]["sensitivity"]
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    ax.loglog(sens["eig_mc"], sens["cost_rise"], "o")
    ax.set(xlabel="eigenvalue of the Monte Carlo covariance", ylabel=f"cost rise, step {sens['extent']:g} along the eigenvector",
           title=f"cf. Figure 4.20 (log-log slope {sens['loglog_slope']:.3f})")
    ax.grid(True, which="both", alpha=0.3)
    save_atomic(fig, os.path.join(OUT, "montecarlo_fourbar3d_sensitivity.png"))


def speed_table(runs):
    """Identifications/s for the four-bar: vmapped vs a loop of the same jitted solve, 1 vs 2 host devices."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import montecarlo

    mc, loop_rate = montecarlo.speed("fourbar3d", runs)
    rate = runs / mc.timings["run_s"]
    try:
        rate2 = montecarlo.two_devices("fourbar3d", runs)
    except Exception as exc:  # noqa: BLE001  (report, do not hide)
        print(f"two-device run failed: {exc}")
        rate2 = float("nan")
    out = {"runs": runs, "compile_s": mc.timings["compile_s"], "vmapped_per_s": rate, "loop_per_s": loop_rate,
           "ratio": rate / loop_rate, "two_host_devices_per_s": rate2}
    print(f"speed fourbar3d ({len(mc.names)} estimated, {runs} runs): compile {out['compile_s']:.1f} s, vmapped {rate:.2f} id/s, "
          f"loop {loop_rate:.2f} id/s, ratio {out['ratio']:.2f}, 2 host devices {rate2:.2f} id/s", flush=True)
    return out


def main(quick=False, speed=False):
    t0 = time.perf_counter()
    runs = 32 if quick else 128
    runs_run3 = 64 if quick else 512
    sweep_runs = 32
    levels_m = [2.5e-11, 1e-9, 2.5e-8, 2.5e-6, 1e-4]  # the s_m of Table 4.2c
    levels_q = [1e-10, 1e-8, 1e-7, 1e-6, 1e-4] if not quick else [1e-10, 1e-7, 1e-4]
    counts = [6, 12, 30, 60] if not quick else [6, 30]
    rb, a_true, q = setup()
    res = {"robot": "fourbar3d", "n_poses": len(q), "device": "pose (frame 5), device frame and tool known",
           "draws_per_run": runs, "draws_run3": runs_run3, "draws_per_sweep_point": sweep_runs, "thesis": THESIS,
           "residual_before": residual_before(rb, a_true, q)}
    print(f"fourbar3d, {len(q)} pose measurements; residual before identification {res['residual_before']:.4f}", flush=True)
    rows, mc3 = table_runs(rb, a_true, q, runs, runs_run3)
    res["table_4_2c"] = rows
    s3 = mc3.summary()
    n3 = int((mc3.converged & mc3.keep).sum())
    res["run3"] = {**s3, "table_4_3": table_4_3(mc3), "estimated": list(mc3.names), "timings": mc3.timings,
                   "similarity_sampling_only": sampling_similarity(mc3.covariance_linear, n3)}
    lam, rise, slope = sensitivities(rb, a_true, q, mc3, TABLE_4_2C[2][0])
    res["run3"]["sensitivity"] = {"extent": 1e-4, "eig_mc": lam, "cost_rise": rise, "loglog_slope": slope}
    # Figure 4.12 traces: runs 1-5 (s_theta = 0) and 6-10 (s_theta = 1e-6) of Table 4.2c, by level
    by = {(r["var_m"], r["var_theta"]): r["residual_median"] for r in rows}
    f12 = {vq: [by[(vm, vq)] for vm in levels_m] for vq in (0.0, 1e-6)}
    res["figure_4_12"] = {"levels_var_m": levels_m, "traces": f12, "crossover_var_m": crossover(levels_m, f12[0.0], f12[1e-6][0])}
    f13 = actuator_sweep(rb, a_true, q, sweep_runs, levels_q)
    res["figure_4_13"] = {"levels_var_theta": levels_q, "traces": f13,
                          "crossover_var_theta": crossover(levels_q, f13[0.0], f13[2.5e-7][0])}
    clean, noisy = count_sweep(rb, a_true, counts, sweep_runs)
    res["figure_4_14"] = {"counts": counts, "noise_free": clean, "noisy": noisy, "var_m": 2.5e-8}
    if speed:
        res["speed"] = speed_table(64)
    res["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["total_s"] = time.perf_counter() - t0
    os.makedirs(OUT, exist_ok=True)
    plots(res, mc3, levels_m, levels_q)
    res["figure_4_12"]["traces"] = {str(k): v for k, v in f12.items()}
    res["figure_4_13"]["traces"] = {str(k): v for k, v in f13.items()}
    write_json_atomic(os.path.join(OUT, "montecarlo_fourbar3d.json"), res)
    report(res)


def report(res):
    r3, th = res["run3"], THESIS
    k = len(r3["estimated"])
    print(f"\nrun 3 (s_m = 2.5e-8, {r3['runs']} draws, {k} estimated parameters)   jaxcal      thesis (26 parameters)")
    print(f"  similarity(linear, Monte Carlo), eq A.56            {r3['similarity']:8.3f}      {th['similarity']}")
    print(f"  same, Gaussian draws of the linear covariance (median, 95 %) {r3['similarity_sampling_only'][0]:.3f}, "
          f"{r3['similarity_sampling_only'][1]:.3f}")
    print(f"  share inside the 95 % ellipsoid                     {r3['inside_95']:8.3f}      {th['inside_95']}")
    print(f"  Mahalanobis radius of the 95 % ellipsoid (chi2_{k})  {r3['radius_95']:8.2f}      {th['radius_95']}")
    print(f"  radius holding 95 % of the draws                    {r3['radius_holding_95']:8.2f}      {th['radius_holding_95']}")
    print(f"  chi-square Q-Q correlation                          {r3['qq_correlation']:8.4f}      (not printed; 'deviates')")
    t43 = r3["table_4_3"]
    print(f"  worst eigenvalue ratio MC/linear: eigenvalue {t43['worst_eigenvalue']}, "
          f"{t43['eig_mc'][t43['worst_eigenvalue'] - 1] / t43['eig_linear'][t43['worst_eigenvalue'] - 1]:.2f} "
          f"(thesis: eigenvalue 4, 27.6, the redundant alpha_2,2)")
    sens = r3["sensitivity"]
    print(f"  cost rise along MC eigenvectors (extent 1e-4) vs eigenvalue: log-log slope {sens['loglog_slope']:.3f} "
          f"(thesis: 'inverse relationship'); rises {min(sens['cost_rise']):.3g} .. {max(sens['cost_rise']):.3g}")
    print(f"  Figure 4.12 crossover s_m at s_theta = 1e-6: {res['figure_4_12']['crossover_var_m']} (thesis ~1e-7)")
    print(f"  Figure 4.13 crossover s_theta at s_m = 2.5e-7: {res['figure_4_13']['crossover_var_theta']} (thesis ~1e-7)")
    print(f"{'parameter':<10}{'diag lin':>11}{'diag MC':>11}{'eig lin':>11}{'eig MC':>11}{'CI width':>11}")
    for i, n in enumerate(t43["names"]):
        print(f"{n:<10}{t43['diag_linear'][i]:>11.3e}{t43['diag_mc'][i]:>11.3e}{t43['eig_linear'][i]:>11.3e}"
              f"{t43['eig_mc'][i]:>11.3e}{t43['ci_width_95_simultaneous'][i]:>11.3e}")
    print(f"total {res['total_s']:.0f} s, peak RSS {res['peak_rss_mib']:.0f} MiB")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--speed", action="store_true", help="also the identifications/s table (montecarlo.speed, 2 devices)")
    ap.add_argument("--thesis-conditions", action="store_true", help="run 3 under conditions (a)-(d) only (issue 16 item 5)")
    ap.add_argument("--draws", type=int, default=128, help="draws per condition with --thesis-conditions")
    ap.add_argument("--only", default="", help="with --thesis-conditions: the letters of the conditions to run, e.g. ab")
    ap.add_argument("--max-steps", type=int, default=50, help="with --thesis-conditions: solver step budget per draw")
    args = ap.parse_args()
    if args.thesis_conditions:
        thesis_conditions(args.draws, args.only, args.max_steps)
    else:
        main(args.quick, args.speed)
