"""Small dense solves in plain `jax.numpy` operations, for the per-sample systems of the loop closures.

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


__all__ = ["solve_small"]
