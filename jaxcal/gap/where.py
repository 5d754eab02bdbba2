"""Where the gap lies: out-of-sample residuals decomposed per axis and per explanatory feature.

For each feature (joint angle, gravity load, covariate, workspace position) a small basis X_f is
regressed on the residual matrix r (N x m, centred): share_f = ||P_f r||^2 / ||r||^2, with the
regression F-test p-value F = (share/(k m)) / ((1 - share)/((N - k - 1) m)). A local smoother over
the workspace (k nearest tip positions) catches structure no basis has; its p-value comes from a
permutation distribution (normal approximation of 400 permutations).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxcal.tails import f_sf, norm_sf


@dataclasses.dataclass
class Feature:
    name: str
    share: float  # share of residual variance explained (R^2)
    p_value: float
    n_basis: int


def _standard(cols):
    X = np.column_stack(cols).astype(float)
    X = X - X.mean(axis=0)
    s = X.std(axis=0)
    return X[:, s > 1e-12] / s[s > 1e-12]


def feature_bases(q, revolute, joint_names, loads, tips, covariates) -> dict:
    """Named bases (N, k) of the features the residual is decomposed on."""
    out = {}
    for j, name in enumerate(joint_names):
        v = q[:, j]
        cols = [f(k * v) for k in (1, 2, 3) for f in (np.sin, np.cos)] if revolute[j] else [v, v**2, v**3]
        out[f"joint angle {name}"] = _standard(cols)
        if loads is not None and np.std(loads[:, j]) > 1e-9:
            out[f"gravity load {name}"] = _standard([loads[:, j]])
    p = tips
    out["workspace position"] = _standard([p[:, 0], p[:, 1], p[:, 2], p[:, 0] ** 2, p[:, 1] ** 2, p[:, 2] ** 2,
                                           p[:, 0] * p[:, 1], p[:, 0] * p[:, 2], p[:, 1] * p[:, 2]])
    for key in ("time", "temperature"):
        if key in covariates:
            c = np.asarray(covariates[key], float)
            out[key] = _standard([c, c**2])
    if "direction" in covariates:
        d = np.asarray(covariates["direction"], float)
        d = d.reshape(len(d), -1)
        if d.shape[1] == 1:
            out["direction"] = _standard([d[:, 0]])
        else:
            for j, name in enumerate(joint_names):
                out[f"direction {name}"] = _standard([d[:, j]])
    return {k: v for k, v in out.items() if v.shape[1] > 0}


def _share(X, r):
    coef, *_ = np.linalg.lstsq(X, r, rcond=None)
    return float(np.sum((X @ coef) ** 2) / max(np.sum(r**2), 1e-300))


def _knn_share(nbr, r):
    pred = r[nbr].mean(axis=1)
    return float(1.0 - np.sum((r - pred) ** 2) / max(np.sum(r**2), 1e-300))


def neighbours(z, k: int) -> np.ndarray:
    """(n, k) indices of each point's k nearest other points (Euclidean), by a KD-tree: O(n log n) time and
    O(n k) memory (the dense n x n distance matrix took 150 MB and an n^2 log n sort at n = 2500)."""
    from scipy.spatial import cKDTree  # imported here: 0.1 s that only this analysis needs

    n = len(z)
    _, idx = cKDTree(z).query(z, k=k + 1)
    keep = idx != np.arange(n)[:, None]
    keep[keep.all(axis=1), -1] = False  # self not among the k + 1 (ties at distance 0): drop the farthest
    return idx[keep].reshape(n, k)


def along(r, directions):
    """Residual component along a unit direction per sample (N, 1), e.g. a joint's motion."""
    return np.sum(r * directions, axis=1, keepdims=True)


def decompose(r, bases: dict, tips, directions=None, k_neighbours: int = 5, n_permutations: int = 400, seed: int = 0) -> list[Feature]:
    """Share of the residual variance each feature explains, with its p-value (most significant first).

    directions: {feature name: (N, m) unit vectors}; for those features the residual component along
    the direction (a joint's motion) is regressed instead of the full residual."""
    r = np.asarray(r, float)
    r = r - r.mean(axis=0)
    n = r.shape[0]
    directions = directions or {}
    feats = []
    for name, X in bases.items():
        k = X.shape[1]
        target = along(r, directions[name]) if name in directions else r
        m = target.shape[1]
        s = _share(X, target - target.mean(axis=0))
        dof = (n - k - 1) * m
        if dof <= 0:
            continue
        F = (s / (k * m)) / max((1 - s) / dof, 1e-300)
        feats.append(Feature(name, s, float(f_sf(F, k * m, dof)), k))
    m = r.shape[1]
    if n > 3 * k_neighbours:
        z = (tips - tips.mean(0)) / np.maximum(tips.std(0), 1e-12)
        nbr = neighbours(z, k_neighbours)
        obs = _knn_share(nbr, r)
        rng = np.random.default_rng(seed)
        null = np.array([_knn_share(nbr, r[rng.permutation(n)]) for _ in range(n_permutations)])
        zscore = (obs - null.mean()) / max(null.std(), 1e-12)
        feats.append(Feature("workspace (local, nearest neighbours)", max(obs, 0.0), float(norm_sf(zscore)), k_neighbours))
    return sorted(feats, key=lambda f: f.p_value)


def axis_rms(r, labels) -> dict:
    """RMS of each residual component, in the given units."""
    return {lab: float(np.sqrt(np.mean(r[:, i] ** 2))) for i, lab in enumerate(labels)}
