"""Host (numpy) or JAX arrays: work on the side an array already lives on.

Host code that runs jax op by op compiles a small XLA program for every operation and shape (~8 ms each on a
2-core CPU); numpy's arrays stay numpy here, and JAX arrays (tracers under jit / vmap included) stay where they are
(Monte Carlo readings drawn on an accelerator are padded and noised there)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def array_module(*values):
    """jax.numpy when any of the values is a JAX array (a tracer under jit / vmap included), else numpy."""
    return jnp if any(isinstance(v, jax.Array) for v in values) else np


def host_or_jax(y):
    """y itself when it is a JAX array (or a tracer), else y as a float numpy array."""
    return y if isinstance(y, jax.Array) else np.asarray(y, dtype=float)
