"""Datasets: joint readings, device readings and covariates, from arrays or CSV."""

from __future__ import annotations

import csv
import os

import numpy as np

from jaxcal.measure.devices import Device, make_device


class DataError(ValueError):
    """Bad input data; the message names the file, row, column or sample."""


def _as_device(device) -> Device:
    return device if isinstance(device, Device) else make_device(device)


def _canonical_readings(device: Device, y, R, p, n: int):
    """Readings as an array of shape (N, *device.reading_shape)."""
    if device.kind == "pose" and y is None:
        if R is None or p is None:
            raise DataError("pose data needs y=(N, 4, 4) or both R=(N, 3, 3) and p=(N, 3)")
        R, p = np.asarray(R, float), np.asarray(p, float)
        y = np.zeros((len(R), 4, 4))
        y[:, :3, :3], y[:, :3, 3], y[:, 3, 3] = R, p, 1.0
    if y is None:
        raise DataError(f"{device.kind} data needs readings y")
    y = np.asarray(y, float)
    if device.kind == "pose" and y.shape[1:] == (3, 4):
        y = np.concatenate([y, np.broadcast_to([[[0, 0, 0, 1.0]]], (len(y), 1, 4))], axis=1)
    if y.shape != (n,) + device.reading_shape:
        raise DataError(f"{device.kind} readings must have shape (N={n}, {', '.join(map(str, device.reading_shape))}), got {y.shape}")
    return y


def _check_finite(arr, what):
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    if bad.any():
        raise DataError(f"{what}: non-finite values in sample(s) {np.flatnonzero(bad)[:10].tolist()}")


class Dataset:
    """Joint values q (N, n_inputs), device readings y and optional covariates.

    `Dataset(q=Q, y=Y, device="position")`; for "pose" give y (N, 4, 4) or R= (N, 3, 3) and
    p= (N, 3). Covariates (e.g. "time", "temperature", "direction") are arrays of length N.
    """

    def __init__(self, q, y=None, device="position", covariates=None, R=None, p=None, joint_names=None, source=None):
        self.device = _as_device(device)
        q = np.asarray(q, float)
        if q.ndim == 1:
            q = q[:, None]
        if q.ndim != 2:
            raise DataError(f"q must be (N, n_inputs), got shape {q.shape}")
        self.q = q
        self.y = _canonical_readings(self.device, y, R, p, len(q))
        _check_finite(self.q, "q")
        _check_finite(self.y, "y")
        self.covariates = {}
        for k, v in (covariates or {}).items():
            v = np.asarray(v)
            if len(v) != len(q):
                raise DataError(f"covariate {k!r} has {len(v)} values for {len(q)} samples")
            self.covariates[k] = v
        self.joint_names = tuple(joint_names) if joint_names is not None else None
        self.source = source

    def __len__(self):
        return len(self.q)

    def __repr__(self):
        cov = f", covariates={sorted(self.covariates)}" if self.covariates else ""
        return f"Dataset(N={len(self)}, n_inputs={self.q.shape[1]}, device={self.device.kind!r}{cov})"

    def subset(self, idx) -> "Dataset":
        idx = np.asarray(idx)
        return Dataset(self.q[idx], self.y[idx], self.device, {k: v[idx] for k, v in self.covariates.items()},
                       joint_names=self.joint_names, source=self.source)

    def split(self, fraction=0.8, seed=0):
        """(train, held-out) random split."""
        perm = np.random.default_rng(seed).permutation(len(self))
        k = int(round(fraction * len(self)))
        return self.subset(np.sort(perm[:k])), self.subset(np.sort(perm[k:]))

    @classmethod
    def from_csv(cls, path, joints, device="position", position_columns=("x", "y", "z"),
                 length_unit="m", angle_unit="rad", covariates=(), delimiter=","):
        """Read a CSV with a header row: joint columns `joints`, the reading columns and covariates.

        Position readings come from `position_columns` (one marker); lengths are converted from
        `length_unit` ("m" or "mm") and joint angles from `angle_unit` ("rad" or "deg") to SI.
        """
        scale = {"m": 1.0, "mm": 1e-3}
        if length_unit not in scale:
            raise DataError(f"{path}: length_unit must be 'm' or 'mm', got {length_unit!r}")
        if angle_unit not in ("rad", "deg"):
            raise DataError(f"{path}: angle_unit must be 'rad' or 'deg', got {angle_unit!r}")
        if not os.path.exists(path):
            raise DataError(f"{path}: no such file")
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh, delimiter=delimiter))
        if not rows:
            raise DataError(f"{path}: empty file")
        header = [h.strip() for h in rows[0]]
        need = list(joints) + list(position_columns) + list(covariates)
        missing = [c for c in need if c not in header]
        if missing:
            raise DataError(f"{path}: missing column(s) {missing}; header has {header}")
        values = []
        for lineno, row in enumerate(rows[1:], start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise DataError(f"{path}, line {lineno}: {len(row)} fields, header has {len(header)}")
            rec = []
            for c in need:
                text = row[header.index(c)].strip()
                try:
                    v = float(text)
                except ValueError:
                    raise DataError(f"{path}, line {lineno}, column {c!r}: not a number: {text!r}") from None
                if not np.isfinite(v):
                    raise DataError(f"{path}, line {lineno}, column {c!r}: non-finite value {text!r}")
                rec.append(v)
            values.append(rec)
        arr = np.array(values, float).reshape(-1, len(need))
        nj, npos = len(joints), len(position_columns)
        q = arr[:, :nj] * (np.pi / 180.0 if angle_unit == "deg" else 1.0)
        y = arr[:, nj:nj + npos] * scale[length_unit]
        cov = {c: arr[:, nj + npos + i] for i, c in enumerate(covariates)}
        return cls(q=q, y=y, device=device, covariates=cov, joint_names=joints, source=str(path))
