"""Plots of a gap diagnosis: residual quiver over the workspace and residual against each joint angle."""

from __future__ import annotations

import json
import os
import tempfile

import numpy as np

from jaxcal.report.plots import plt, save_atomic


def _quiver(ax, tips, res, i, j, title):
    p = tips * 1e3
    norm = np.linalg.norm(res[:, :3], axis=1)
    sc = ax.scatter(p[:, i], p[:, j], c=norm, s=12, cmap="viridis")
    span = max(np.ptp(p[:, i]), np.ptp(p[:, j]), 1e-9)
    k = 0.08 * span / max(np.percentile(norm, 95), 1e-12)  # longest arrows ~8 % of the workspace
    ax.quiver(p[:, i], p[:, j], k * res[:, i], k * res[:, j], angles="xy", scale_units="xy", scale=1, width=0.003, alpha=0.8)
    ax.set_xlabel("xyz"[i] + " (mm)")
    ax.set_ylabel("xyz"[j] + " (mm)")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    return sc


def plot_diagnosis(d, folder) -> list[str]:
    """Write quiver.png, joints.png and diagnosis.json into `folder`; returns the paths."""
    pdata = d.plot_data
    tips, q = pdata["tips"], pdata["q"]
    before, after = pdata["oof_base"], pdata["oof_final"]
    os.makedirs(folder, exist_ok=True)
    paths = []

    fig, axes = plt.subplots(2, 2, figsize=(11, 10))
    for row, (res, label) in enumerate([(before, "geometry only"), (after, f"with {d.verdict}")]):
        for col, (i, j) in enumerate([(0, 1), (0, 2)]):
            sc = _quiver(axes[row, col], tips, res, i, j, f"held-out position residual, {label} (arrows scaled)")
        fig.colorbar(sc, ax=axes[row, :].tolist(), label="|residual| (mm)", shrink=0.8)
    fig.suptitle(f"{d.robot_name}: verdict {d.verdict} {', '.join(d.joints)}  "
                 f"(held-out RMS {d.heldout_rms_before:.3g} -> {d.heldout_rms_after:.3g} mm)")
    paths.append(save_atomic(fig, os.path.join(folder, "quiver.png")))

    nj = q.shape[1]
    fig, axes = plt.subplots(nj, 1, figsize=(8, 2.2 * nj), squeeze=False)
    for j in range(nj):
        ax = axes[j, 0]
        x = np.degrees(q[:, j]) if pdata["revolute"][j] else q[:, j] * 1e3
        u = pdata["motion"][:, :, j]
        ax.plot(x, np.sum(before * u, axis=1), ".", color="tab:red", ms=4, label="geometry only")
        ax.plot(x, np.sum(after * u, axis=1), "+", color="k", ms=4, label=f"with {d.verdict}")
        ax.set_xlabel(f"{pdata['joint_names'][j]} ({'deg' if pdata['revolute'][j] else 'mm'})")
        ax.set_ylabel("along motion (mm)")
        ax.axhline(0, color="0.6", lw=0.5)
    axes[0, 0].legend(fontsize=8, ncol=2, loc="upper right")
    fig.suptitle("held-out residual component along each joint's motion, against the joint value", fontsize=10)
    fig.tight_layout()
    paths.append(save_atomic(fig, os.path.join(folder, "joints.png")))

    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".json")
    with os.fdopen(fd, "w") as fh:
        json.dump(d.to_dict(), fh, indent=1)
    out = os.path.join(folder, "diagnosis.json")
    os.replace(tmp, out)
    paths.append(out)
    return paths
