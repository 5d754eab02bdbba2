"""`jaxcal demo`: end-to-end calibrations of two built-in robots on simulated data.

1. MRR-1 (seed 000 Table 6.1) with errors N(0, 0.003) on body vectors and PRY angles as in
   seed 000 §6, full-pose measurements in the robot's world frame (as in the seed).
2. Stanford arm (seed 001 Table 1) with a laser tracker: position of a marker, tracker frame and
   marker offset unknown and identified with the geometry.
Each prints a report, checks the calibrated model on held-out configurations and writes plots.
"""

from __future__ import annotations

import os
import time

import numpy as np

import jaxcal as jc
from jaxcal.report import plot_convergence, plot_errors_before_after, write_text_atomic


def _case(title, robot, a_true, device, noise, n_train, n_test, known, out, tag, seed):
    q_train = jc.random_configurations(robot, n_train, seed=seed, margin=0.05)
    q_test = jc.random_configurations(robot, n_test, seed=seed + 1, margin=0.05)
    train = jc.simulate(robot, a_true, q_train, device, noise=noise, seed=seed + 2)
    test = jc.simulate(robot, a_true, q_test, device, noise=noise, seed=seed + 3)
    sp = noise.get("position", 1e-3) or 1e-3
    so = noise.get("orientation", 1e-3) or 1e-3
    fit = jc.identify(robot, train, known=known, sigma_position=sp, sigma_orientation=so, history=True)
    nominal = jc.identify(robot, train, known=known, free=(), sigma_position=sp, sigma_orientation=so)
    before_test, after_test = nominal.errors(test)[0], fit.errors(test)[0]
    lines = [
        f"== {title} ==",
        fit.report(),
        f"held-out ({n_test} new configurations): position RMS {np.sqrt(np.mean(before_test**2)) * 1e3:.4g} mm "
        f"(nominal) -> {np.sqrt(np.mean(after_test**2)) * 1e3:.4g} mm (calibrated); "
        f"noise {noise.get('position', 0) * 1e3:.3g} mm",
        "",
        fit.parameter_table(a_true=np.concatenate([np.asarray(a_true), np.asarray(fit.device.nominal_np)])),
        "",
    ]
    text = "\n".join(lines)
    print(text)
    plot_convergence(fit.history, os.path.join(out, f"{tag}_convergence.png"), f"{title}: convergence")
    plot_errors_before_after(before_test * 1e3, after_test * 1e3, os.path.join(out, f"{tag}_errors.png"),
                             "mm", f"{title}: held-out position error")
    return text


def run(out: str = "demo-output") -> str:
    t0 = time.perf_counter()
    os.makedirs(out, exist_ok=True)
    mrr1 = jc.robots.get("mrr1")
    a_mrr1 = jc.perturb(mrr1, 0.003, seed=6)
    text = _case("MRR-1, full pose (seed 000 §6)", mrr1, a_mrr1, "pose",
                 {"position": 2e-5, "orientation": 2e-5}, 50, 30, ("dev",), out, "mrr1", 10)
    st = jc.robots.get("stanford")
    a_st = jc.perturb(st, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=7)
    text += _case("Stanford arm, laser tracker (seed 001 Table 1)", st, a_st, "tracker",
                  {"position": 2e-5}, 100, 50, (), out, "stanford", 20)
    text += f"\ndemo finished in {time.perf_counter() - t0:.1f} s; plots in {os.path.abspath(out)}\n"
    print(text.splitlines()[-1])
    write_text_atomic(os.path.join(out, "report.txt"), text)
    return text
