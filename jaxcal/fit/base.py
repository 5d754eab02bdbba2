"""Base (identifiable) parameters by QR of the observation matrix (seed 001 Appendix III).

Columns are ordered by priority (highest first, stable in the table order), then a QR
decomposition without pivoting keeps a column when |R_ii| > tau = c * eps * max|R_jj| (eq 34):
the base set is the first independent columns in priority order. Regrouping relations follow
from beta = R1^-1 R2 (eq 37); columns whose norm is below tau have no effect at all.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
from scipy.linalg import lapack


@dataclasses.dataclass(frozen=True)
class BaseSet:
    """Which columns of W form the base, which have no effect and which are regrouped."""

    independent: np.ndarray  # column indices of the base set, in priority order
    no_effect: np.ndarray  # columns with no effect on the model (zero column)
    regrouped: np.ndarray  # columns dependent on the base set
    beta: np.ndarray  # (len(independent), len(regrouped)): W_regrouped = W_base @ beta
    tau: float
    diag: np.ndarray  # |R_ii| in the ordered column sequence
    order: np.ndarray  # the column order used


def upper_factor(A, overwrite: bool = False) -> np.ndarray:
    """R (min(n, k) x k), upper triangular, of A = Q R for A (n, k), by LAPACK's dgeqrf on A in column-major order,
    Q not formed. overwrite: A is a column-major float64 temporary of the caller's, factored in place (no copy).
    scipy.linalg.qr(mode="r") also returns R's n - k rows of zeros, and numpy.linalg.qr copies A to column-major
    itself (Stanford arm, 200 poses, this 2-core CPU: `base_set` of the 1200 x 46 start Jacobian 0.40 -> 0.33 ms in
    an identify process; a whole identify with `core.triangular` too, -0.15 ms)."""
    A = np.asfortranarray(A, dtype=np.float64) if overwrite else np.array(A, dtype=np.float64, order="F")
    if not A.size:
        return np.zeros((min(A.shape), A.shape[1]))
    qr, _, _, info = lapack.dgeqrf(A, overwrite_a=True)
    if info != 0:
        raise np.linalg.LinAlgError(f"dgeqrf failed (info {info})")
    return np.triu(qr[:min(A.shape)])


def small_lstsq(A, B) -> np.ndarray:
    """A least-squares solution X of A X ~ B for a small A (tens of rows and columns), of minimum norm where A is
    rank deficient (rank by the condition estimate of A's column-pivoted QR, cut-off eps max(m, n) as numpy's lstsq:
    LAPACK's dgelsy). The factors `base_set` and `core.linear_f_ratio` solve on are ~56 x 55: dgelsy 58 us against
    numpy's SVD-based dgelsd 230 us (this 2-core CPU), run several times in every identify."""
    return scipy.linalg.lstsq(A, B, cond=np.finfo(float).eps * max(np.shape(A)), lapack_driver="gelsy", check_finite=False)[0]


def priority_order(priority) -> np.ndarray:
    """Column order: higher priority first, ties kept in table order; priority 0 dropped."""
    priority = np.asarray(priority, float)
    idx = np.flatnonzero(priority > 0)
    return idx[np.argsort(-priority[idx], kind="stable")]


def base_set(W, priority, c: float | None = None) -> BaseSet:
    """Base set of the columns of W under the given priorities (seed 001 eq 33-37)."""
    W = np.asarray(W, float)
    order = priority_order(priority)
    Wo = W.T[order].T  # the ordered columns, copied once into column-major order for `upper_factor`
    col_norm = np.linalg.norm(Wo, axis=0)
    R = upper_factor(Wo, overwrite=True) if Wo.size else np.zeros((0, 0))  # Wo is overwritten
    cols = Wo.shape[1]
    # Fewer rows than columns: R has min(m, n) pivots; the columns past the m-th are dependent.
    diag = np.zeros(cols)
    if R.size:
        diag[: min(R.shape)] = np.abs(np.diag(R))
    scale = np.max(diag) if diag.size else 0.0
    tau = (cols if c is None else c) * np.finfo(float).eps * scale
    keep = diag > tau
    zero = col_norm <= tau
    independent = order[keep]
    dependent_pos = np.flatnonzero(~keep & ~zero)
    regrouped = order[dependent_pos]
    if regrouped.size and independent.size:  # W = Q R with Q's columns orthonormal: solved on R's rows (eq 37)
        beta = small_lstsq(R[:, keep], R[:, dependent_pos])
    else:
        beta = np.zeros((independent.size, regrouped.size))
    return BaseSet(independent, order[zero], regrouped, beta, float(tau), diag, order)


def numerical_rank(W, c: float | None = None) -> int:
    """Rank of W by SVD under the threshold rule of `base_set`: singular values above c eps s_max (default
    c = number of columns). The same relative threshold as the QR pivots of eq 34, so the two agree wherever
    the spectrum has a gap at it; a caller that compares them should pass the same c (core.BASE_TOL / eps)."""
    W = np.asarray(W, float)
    if not W.size:
        return 0
    s = np.linalg.svd(W, compute_uv=False)
    tau = (W.shape[1] if c is None else c) * np.finfo(float).eps * s[0]
    return int(np.sum(s > tau))


def regrouping_relations(bs: BaseSet, names, tol: float = 1e-8) -> list[str]:
    """Readable relations 'base_k absorbs + b * regrouped_j' from beta (eq 32, 37)."""
    out = []
    for i, bi in enumerate(bs.independent):
        terms = [f"{bs.beta[i, j]:+.6g} {names[rj]}" for j, rj in enumerate(bs.regrouped) if abs(bs.beta[i, j]) > tol]
        if terms:
            out.append(f"{names[bi]}_b = {names[bi]} " + " ".join(terms))
    return out
