"""Shared helpers for the benchmarks: timing with medians, a numpy Stanford model."""

from __future__ import annotations

import os
import statistics
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402


def median_time(fn, repeat: int = 5, number: int = 1) -> float:
    """Median wall time of `number` calls of fn, over `repeat` repetitions (seconds per call)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - t) / number)
    return statistics.median(times)


def first_and_median(fn, repeat: int = 3):
    """(result, seconds of the first call (compile included), median seconds of `repeat` more calls)."""
    t = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t
    return out, first, median_time(fn, repeat=repeat)


def _rx(t):
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _ry(t):
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(t), np.zeros_like(t)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def stanford_fk_numpy(a, q):
    """Hand-vectorised numpy forward kinematics of the Stanford arm (seed 001 eq 3), same
    parameter layout as jc.robots.get("stanford"): returns R (N, 3, 3), p (N, 3)."""
    n = q.shape[0]
    th0, r0 = a[0], a[1]
    R = np.broadcast_to(_rz(np.array(th0)), (n, 3, 3)).copy()
    p = np.tile(np.array([0.0, 0.0, r0]), (n, 1))
    gains = a[37:43]
    for j in range(1, 8):
        alpha, d, theta, r, beta = a[2 + 5 * (j - 1): 7 + 5 * (j - 1)]
        th = np.full(n, theta)
        rr = np.full(n, r)
        if j <= 6:
            qj = gains[j - 1] * q[:, j - 1]
            if j == 3:
                rr = rr + qj
            else:
                th = th + qj
        Ryb = _ry(np.array(beta))
        Rxa = _rx(np.array(alpha))
        # origin of frame j in frame j-1: Ry(beta) ([d, 0, 0] + Rx(alpha) [0, 0, r])
        off = (Ryb @ np.array([d, 0.0, 0.0]))[None, :] + (Ryb @ Rxa @ np.array([0.0, 0.0, 1.0]))[None, :] * rr[:, None]
        p = p + np.einsum("nij,nj->ni", R, off)
        R = R @ (Ryb @ Rxa)[None] @ _rz(th)
    return R, p


def exp_so3_numpy(w):
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def log_so3_numpy(R):
    """Rotation vectors of a batch of rotations (N, 3, 3), away from a half turn."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)
    ang = np.arccos(c)
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    f = np.where(ang < 1e-8, 1.0, ang / np.where(ang < 1e-8, 1.0, np.sin(ang)))
    return f[:, None] * v
