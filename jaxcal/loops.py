"""Loop carries that vary with an input, so that `vmap` of a `jax.lax.while_loop` traces its body fewer times.

`vmap` batches a while loop by a fixpoint over which carry entries are batched (jax `_while_loop_batching_rule`;
`scan`, and so `fori_loop` with fixed bounds, alike):
it batches the body with the entries batched at the start, again with those the body's output makes batched, and
once more to build the loop it runs. A carry started from constants (zeros, a counter, a flag) next to a batched
input therefore costs three batchings of the body instead of two, and a loop nested in another's body is batched
once per batching of the outer body: three levels of loops cost 27 batchings of the innermost body instead of 8.
The Delta's batch closure (`jaxcal.closure.delta.forward`: the corrector loop of `track` in its path loop, in the
chunk loop of `tracked_samples`) traced in 2.6 s, 1.3 s with its carries tied to the batched start
(docs/benchmarks.md, twenty-third session).

The loop the batched rule builds is the same either way: with a batched predicate (every loop here stops per
lane) every carry entry ends up batched, so tying the start changes no computation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def varying_with(x, carry):
    """carry, each leaf tied to x by `select(isnan(x[0]), leaf, leaf)`: the same values (XLA folds the select away),
    batched under `vmap` wherever x is, so that a while loop's batching rule finds its fixpoint on the first pass."""
    x = jnp.asarray(x)
    if x.size == 0:
        return carry
    flag = jnp.isnan(x.ravel()[0])
    return jax.tree_util.tree_map(lambda v: jax.lax.select(jnp.broadcast_to(flag, jnp.shape(v)), v, v), carry)


__all__ = ["varying_with"]
