"""Plots written by the demo and the CLI (matplotlib, Agg backend, atomic writes)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxcal.io_atomic import atomic_path, write_text_atomic  # noqa: E402,F401


def plain_text(text) -> str:
    """A string from an input (a robot name) shown literally in a matplotlib title: `$` would start
    mathtext (and a malformed formula fails the whole plot), control characters become spaces."""
    return "".join(" " if ord(c) < 32 else c for c in str(text)).replace("$", r"\$")


def save_atomic(fig, path: str, dpi: int = 120) -> str:
    """Save a figure to a temp file beside `path`, then rename: no half-written file is left. A figure with a
    layout engine (constrained layout) is already fitted to its canvas; others are cropped to their content
    ("tight", which draws the figure twice: 0.1-0.3 s a figure on this machine)."""
    tight = None if fig.get_layout_engine() is not None else "tight"
    try:
        with atomic_path(path, suffix=os.path.splitext(path)[1]) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches=tight)
    finally:
        plt.close(fig)
    return path


def plot_convergence(history, path: str, title: str = "convergence"):
    """Cost (sum of squared weighted residuals) per solver step, log scale."""
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    h = np.maximum(np.asarray(history), 1e-300)
    ax.semilogy(np.arange(len(h)), h, "o-", ms=3)
    ax.set_xlabel("solver step")
    ax.set_ylabel("cost  sum (r / sigma)^2")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    return save_atomic(fig, path)


def plot_errors_before_after(before, after, path: str, unit: str = "mm", title: str = "error per configuration"):
    """Bar chart of the per-configuration error before and after calibration."""
    before, after = np.asarray(before), np.asarray(after)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    idx = np.arange(len(before))
    ax.bar(idx - 0.2, before, width=0.4, label=f"before (RMS {np.sqrt(np.mean(before ** 2)):.3g} {unit})")
    ax.bar(idx + 0.2, after, width=0.4, label=f"after (RMS {np.sqrt(np.mean(after ** 2)):.3g} {unit})")
    ax.set_yscale("log")
    ax.set_xlabel("configuration")
    ax.set_ylabel(f"error [{unit}]")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    return save_atomic(fig, path)


def plot_ga_history(best, mean, path: str, title: str = "GA fitness per generation"):
    """Best and mean fitness per generation (seed 000 Figure 6.9), log scale."""
    fig, ax = plt.subplots(figsize=(6.5, 4))
    g = np.arange(1, len(best) + 1)
    ax.semilogy(g, np.asarray(mean), color="tab:blue", lw=1.2, label=f"mean (final {mean[-1]:.3g})")
    ax.semilogy(g, np.asarray(best), color="black", lw=1.8, label=f"best (final {best[-1]:.3g})")
    ax.set_xlabel("generation")
    ax.set_ylabel("fitness  sum ||P_m - P_0|| + ||R_m - R_0||_2")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_atomic(fig, path)


def plot_ga_population_study(curves: dict, path: str, title: str = "GA: population and generations"):
    """Best fitness per generation for several (population, generations) settings (seed 000 Figure 6.10).
    curves: label -> (G,) best fitness (e.g. the median over runs)."""
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for label, best in curves.items():
        best = np.asarray(best)
        ax.semilogy(np.arange(1, len(best) + 1), best, lw=1.5, label=f"{label}: final {best[-1]:.3g}")
    ax.set_xlabel("generation")
    ax.set_ylabel("best fitness (median over runs)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_atomic(fig, path)


def plot_monte_carlo_level1(running_mean, changes: dict, tols: dict, path: str, unit_scale: float = 1e3,
                            title: str = "Monte Carlo level 1"):
    """(a) running means of every identified error over the GA runs (seed 000 Figure 6.11);
    (b) the eq 5.7 change of the running mean per run for each stopping quantity, with its tolerance."""
    rm = np.asarray(running_mean) * unit_scale
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    runs = np.arange(1, rm.shape[0] + 1)
    a.set_prop_cycle(color=plt.cm.tab20(np.linspace(0, 1, 20)))
    a.plot(runs, rm, lw=1)
    a.set_xlabel("GA runs k")
    a.set_ylabel("running mean of dg (mm / mrad)")
    a.set_title("(a) running mean of each parameter error")
    a.grid(True, alpha=0.3)
    for (label, change), color in zip(changes.items(), ("tab:red", "tab:green", "tab:blue")):
        change = np.asarray(change)
        b.semilogy(np.arange(2, len(change) + 2), change, "o-", ms=3, color=color, label=label)
        b.axhline(tols[label], color=color, ls="--", lw=1, label=f"tolerance L1 = {tols[label]:g}")
    b.set_xlabel("GA runs k")
    b.set_ylabel("max |mean_k - mean_(k-1)|  (eq 5.7)")
    b.set_title("(b) change of the running mean")
    b.grid(True, which="both", alpha=0.3)
    b.legend(fontsize=8)
    fig.suptitle(title)
    return save_atomic(fig, path)


def plot_monte_carlo_level2(running_global, names, tip_error, path: str, stable=None, unit_scale: float = 1e3,
                            title: str = "Monte Carlo level 2"):
    """(a) running global mean (eq 5.10) of each identified error as configuration sets are added
    (seed 000 Figure 6.12), dashed where the parameter is not stable (`stable` mask, eq 5.7);
    (b) per set, the error of the tip positions its level-1 runs predict at check configurations."""
    running_global = np.asarray(running_global) * unit_scale
    sets = np.arange(1, running_global.shape[0] + 1)
    stable = np.ones(len(names), bool) if stable is None else np.asarray(stable)
    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw={"width_ratios": [3, 2], "wspace": 0.7})
    a.set_prop_cycle(color=plt.cm.tab20(np.linspace(0, 1, 20)))
    for i, name in enumerate(names):
        a.plot(sets, running_global[:, i], "-" if stable[i] else "--", lw=1, label=name if stable[i] else f"{name} (unstable)")
    a.set_xlabel("configuration sets")
    a.set_ylabel("global mean of dg, eq 5.10 (mm / mrad)")
    a.set_title("(a) running global mean over configuration sets")
    a.grid(True, alpha=0.3)
    a.legend(fontsize=6.5, ncol=1, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    b.bar(sets, np.asarray(tip_error) * unit_scale, color="tab:green")
    b.set_xlabel("configuration set")
    b.set_ylabel("max error, mean predicted tip (mm)")
    b.set_title("(b) predicted tip positions vs truth")
    b.grid(True, axis="y", alpha=0.3)
    fig.suptitle(title)
    return save_atomic(fig, path)
