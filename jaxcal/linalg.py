"""Small dense solves in plain `jax.numpy` operations, for the per-sample systems of the loop closures: general
square systems (`solve_small`) and symmetric positive definite ones (`solve_spd`).

Why not `jnp.linalg.solve`: on CPU, XLA runs a batched LU (what `vmap` of `jnp.linalg.solve` lowers to) as a
LAPACK custom call that fans its batch out over the intra-op thread pool it is itself running on and waits
for the parts. When as many such calls run at once as the pool has threads (two on a 2-core machine; the
Jacobian of a vmapped closure schedules many independent solves), every worker waits for a free worker and
the process hangs with all threads idle (seen in `jc.gap.diagnose` on the Delta with 193-300 samples).
Gaussian elimination written out in array operations has no custom call, vectorises under `vmap`, runs
unchanged on GPU and is differentiated by ordinary autodiff.
"""

from __future__ import annotations

import jax.numpy as jnp


def solve_small(A, b):
    """x with A x = b for a small square A (n, n) (n up to a few tens; the loop is unrolled over n) and
    b (n,) or (n, k), by Gaussian elimination with partial pivoting (row swaps choose the largest
    |pivot| of each column, the backward-stable variant; Golub & Van Loan, Algorithm 3.4.1).

    A singular A gives non-finite entries, as `jnp.linalg.solve` does; callers check `isfinite`."""
    n = A.shape[-1]
    if A.shape != (n, n) or b.shape[0] != n:
        raise ValueError(f"solve_small: A must be square and b must have {n} rows, got A {A.shape}, b {b.shape}")
    vector = b.ndim == 1
    M = jnp.concatenate([A, b[:, None] if vector else b], axis=1)
    rows = jnp.arange(n)[:, None]
    for k in range(n - 1):
        p = k + jnp.argmax(jnp.abs(M[k:, k]))
        # the swap as selects on the row index, not a gather and a scatter at p: under vmap each is a loop over the
        # batch at a batched position (the Delta's fit program: 24 -> 8 loops, LLVM IR 139k -> 123k lines)
        row_k, row_p = M[k], jnp.sum(jnp.where(rows == p, M, 0.0), axis=0)
        M = jnp.where(rows == k, row_p, jnp.where(rows == p, row_k, M))
        factors = M[k + 1:, k] / M[k, k]
        M = M.at[k + 1:].add(-factors[:, None] * M[k])
    U, c = M[:, :n], M[:, n:]
    x = jnp.zeros_like(c)
    for i in range(n - 1, -1, -1):  # back substitution; rows of x below i are still zero, so U[i] @ x sums j > i
        x = x.at[i].set((c[i] - U[i] @ x) / U[i, i])
    return x[:, 0] if vector else x


def solve_spd(A, b):
    """x with A x = b for a small symmetric positive definite A (n, n) and b (n,), by Cholesky A = L L^T and two
    triangular solves, written out entry by entry (Golub & Van Loan, Algorithm 4.2.1; no pivoting: Cholesky is
    backward stable on SPD matrices). For the normal equations J^T J (+ mu I) of the closures' Newton steps: the
    entries' arithmetic fuses into a few kernels, where `solve_small`'s row swaps compile kernels of their own (the
    Delta's closure program: LLVM IR 71k -> 64k lines).

    An A that is not positive definite to working precision (a singular J^T J) gives non-finite entries; callers
    check `isfinite`."""
    n = A.shape[-1]
    if A.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"solve_spd: A must be square and b a vector of its {n} rows, got A {A.shape}, b {b.shape}")
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        pivot = A[j, j] - sum(L[j][k] ** 2 for k in range(j))
        L[j][j] = jnp.sqrt(jnp.where(pivot > 0, pivot, jnp.nan))
        for i in range(j + 1, n):
            L[i][j] = (A[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    y = []  # L y = b
    for i in range(n):
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n  # L^T x = y
    for i in range(n - 1, -1, -1):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return jnp.stack(x)


__all__ = ["solve_small", "solve_spd"]
