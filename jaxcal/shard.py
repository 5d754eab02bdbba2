"""Batched work split across the devices JAX sees (docs/scale-out.md).

`over_devices(fn, batched, shared, devices)` runs `fn` on equal slices of the leading axis of
`batched`, one slice committed to each device with `jax.device_put` (so each device runs its own
while loops and never waits on the others), and concatenates the results in order. On accelerators
the slices are dispatched asynchronously and run at the same time; on host CPU devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=N`) they run one after the other, because
concurrent while-loop programs, and a jit over a NamedSharding of a vmapped while loop,
deadlocked on two host devices (measured on the 2-core CI machine; docs/scale-out.md).
"""

from __future__ import annotations

import jax
import numpy as np


def over_devices(fn, batched, shared, devices=None):
    """fn(batched_slice, shared) on each device's slice of the leading axis; results concatenated.

    `batched`: a pytree of arrays with a common leading axis (its length must divide evenly by the
    number of devices: pad it); `shared`: a pytree given whole to every device. `devices`: default
    all of `jax.devices()`; one device (or []) runs `fn` once without splitting.
    """
    devices = list(jax.devices() if devices is None else devices)
    if len(devices) <= 1:
        return jax.tree_util.tree_map(np.asarray, fn(batched, shared))
    n = len(jax.tree_util.tree_leaves(batched)[0])
    if n % len(devices):
        raise ValueError(f"the batch of {n} does not split evenly over {len(devices)} devices; pad it")
    concurrent = devices[0].platform != "cpu"
    k = n // len(devices)
    outs = []
    for i, d in enumerate(devices):
        part = jax.tree_util.tree_map(lambda x: jax.device_put(np.asarray(x)[i * k:(i + 1) * k], d), batched)
        out = fn(part, jax.device_put(shared, d))
        outs.append(out if concurrent else jax.block_until_ready(out))
    return jax.tree_util.tree_map(lambda *v: np.concatenate([np.asarray(x) for x in v]), *outs)


__all__ = ["over_devices"]
