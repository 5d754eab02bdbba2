"""Sample-count buckets: the compiled programs of a robot and device are built for a few sample counts, not for each.

A program compiled for N samples serves every dataset of N samples only, so a second dataset of 198 samples after
one of 200 compiled the solver again (~3 s for the Stanford arm, ~14 s for the Delta). Here a dataset of n samples
runs in the program for `sample_bucket(n)` samples: n rounded up to one of `SAMPLE_BUCKETS_PER_OCTAVE` sizes per
octave (16: under 6.25 % padding rows; 197 to 200 samples run in the program for 200, 121 to 124 in that for 124,
61 in that for 62). The padding rows repeat a sample that is in use (its joint values, readings and covariates),
with weight 0: their residual rows are exactly 0, so the stacked residual's norm, its Jacobian's non-zero rows, every
LM step and the optimum are those of the n samples (`jaxcal.fit.core`'s module docstring: a weight of 0 removes a
sample exactly). A repeated sample closes, or fails to, exactly as the sample it repeats, so closed mechanisms need
nothing more. Callers slice the outputs back to their n samples. JAXCAL_SAMPLE_BUCKETS sets the number of sizes per
octave (a power of 2; 0: every sample count its own program).
"""

from __future__ import annotations

import os

import numpy as np

from jaxcal.arrays import array_module

SAMPLE_BUCKETS_PER_OCTAVE = int(os.environ.get("JAXCAL_SAMPLE_BUCKETS", "16"))
SAMPLE_ARRAYS = ("q", "y", "cov")  # solver arguments with one row per sample, padded by repeating a sample in use


def sample_bucket(n: int, per_octave: int | None = None) -> int:
    """The sample count of the program that runs n samples: n rounded up to a multiple of 2^(floor(log2(n - 1)) - k)
    with per_octave = 2^k sizes per octave (a power of 2; default SAMPLE_BUCKETS_PER_OCTAVE; 0, or n <= per_octave:
    n itself)."""
    per_octave = SAMPLE_BUCKETS_PER_OCTAVE if per_octave is None else per_octave
    if per_octave <= 0 or n <= per_octave:
        return n
    step = 1 << max(int(n - 1).bit_length() - int(per_octave).bit_length(), 0)
    return -(-n // step) * step


def repeat_row(a, size: int, row: int, axis: int = 0):
    """a with its `axis` extended to `size` by copies of index `row` along it."""
    xp = array_module(a)
    a = xp.asarray(a)
    extra = size - a.shape[axis]
    if extra <= 0:
        return a
    copies = xp.repeat(xp.take(a, xp.asarray([row]), axis=axis), extra, axis=axis)
    return xp.concatenate([a, copies], axis=axis)


def zero_rows(a, size: int, axis: int = 0):
    """a with its `axis` extended to `size` by zeros."""
    xp = array_module(a)
    a = xp.asarray(a)
    shape = list(a.shape)
    shape[axis] = size - a.shape[axis]
    return a if shape[axis] <= 0 else xp.concatenate([a, xp.zeros(shape, a.dtype)], axis=axis)  # np.pad: 3x slower


def row_in_use(w, axis: int = 0) -> int:
    """The first sample (index along `axis` of the weights w) with a non-zero weight in any batch entry, else 0."""
    w = np.asarray(w)
    used = np.any(w != 0, axis=tuple(i for i in range(w.ndim) if i != axis))
    return int(np.argmax(used))


def padded_solver_args(args: dict, batched=(), placeholder=None) -> dict:
    """The core solver's arguments (`jaxcal.fit.core.Problem.solver_arrays`) for the bucket of their sample count:
    q, y and cov repeat a sample in use, w (weights) and the start's data rows (r (N*m,), J (N*m, P)) are 0 past
    the n samples. An entry named in `batched` has its samples on axis 1. placeholder(shape): the zeros standing in
    for a start not given (`core.zeros_placeholder`), made at the padded shape rather than padded."""
    axis = {k: 1 if k in batched else 0 for k in (*SAMPLE_ARRAYS, "w")}
    n = np.shape(args["q"])[axis["q"]]
    size = sample_bucket(n)
    if size == n:
        return args
    row = row_in_use(args["w"], axis["w"])
    out = dict(args, w=zero_rows(args["w"], size, axis["w"]))
    for k in SAMPLE_ARRAYS:
        out[k] = repeat_row(args[k], size, row, axis[k])
    if "start" in args:
        start = args["start"]
        rows = np.shape(start["r"])[0] // max(n, 1) * size
        if float(start["given"]) or placeholder is None:
            out["start"] = dict(start, r=zero_rows(start["r"], rows), J=zero_rows(start["J"], rows))
        else:
            out["start"] = dict(start, r=placeholder((rows,)), J=placeholder((rows, np.shape(start["J"])[1])))
    return out


__all__ = ["SAMPLE_BUCKETS_PER_OCTAVE", "padded_solver_args", "repeat_row", "row_in_use", "sample_bucket", "zero_rows"]
