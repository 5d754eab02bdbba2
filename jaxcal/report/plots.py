"""Plots written by the demo and the CLI (matplotlib, Agg backend, atomic writes)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxcal.io_atomic import atomic_path, write_text_atomic  # noqa: E402,F401


def save_atomic(fig, path: str, dpi: int = 120) -> str:
    """Save a figure to a temp file beside `path`, then rename: no half-written file is left."""
    try:
        with atomic_path(path, suffix=os.path.splitext(path)[1]) as tmp:
            fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
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
