"""Scale-out: batched work split across the devices JAX sees (docs/scale-out.md).

`over_devices(fn, batched, shared, devices)` runs a vmapped, jitted `fn` on equal slices of the
leading axis of `batched`, one slice committed to each device with `jax.device_put` (so each
device runs its own while loops and never waits on the others), and concatenates the results in
order. On accelerators the slices are dispatched asynchronously and run at the same time; on
host CPU devices (`XLA_FLAGS=--xla_force_host_platform_device_count=N`) they run one after the
other, because concurrent while-loop programs, and a jit over a NamedSharding of a vmapped while
loop, deadlocked on two host devices (shared JAX_NOTES; `jaxcal.fit.uncertainty` does the same).

`identify_fleet` uses it to calibrate many robots of one model at once (one dataset each, same
number of samples): the vmapped LM of `jaxcal.fit.identify`, sharded over the devices.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit.identify import _rms_residual, _solve, _x_scale, identify, residual_weights, residuals


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


@functools.partial(jax.jit, static_argnames=("robot", "device", "solver", "max_steps", "rtol", "atol"))
def _solve_fleet(batched, shared, *, robot, device, solver, max_steps, rtol, atol):
    """Vmapped LM over robots: each has its own joint values, readings and weights."""
    def one(b):
        args = dict(shared, q=b["q"], y=b["y"], w=b["w"])
        return _solve.__wrapped__(shared["x0"], args, robot=robot, device=device, solver=solver, max_steps=max_steps,
                                  rtol=rtol, atol=atol)

    return jax.vmap(one)(batched)


@dataclasses.dataclass
class FleetResult:
    """Per robot: the full parameter vector (robot + device), convergence and position RMS (mm)."""

    names: tuple[str, ...]
    a_full: np.ndarray  # (n_robots, n_params)
    converged: np.ndarray
    iterations: np.ndarray
    rms_after: np.ndarray  # (n_robots,) position RMS of the calibrated model on its own data, mm
    estimated: tuple[str, ...]
    timings: dict


def identify_fleet(robot, datasets, devices=None, sigma_position=1e-3, sigma_orientation=1e-3, solver="lm",
                   max_steps=100, rtol=1e-8, atol=1e-10) -> FleetResult:
    """Identify one robot model from several datasets (one per physical robot), sharded over devices.

    The estimated set and the starting point come from `identify` on the first dataset; every robot
    is then solved from there with the same model (parameters outside the estimated set stay at the
    first robot's values; the estimated ones absorb the difference, as in the base-set regrouping).
    All datasets need the same number of samples and device kind.
    """
    t0 = time.perf_counter()
    n = len(datasets[0])
    if any(len(d) != n or type(d.device) is not type(datasets[0].device) for d in datasets):
        raise ValueError("identify_fleet needs datasets of equal size and device kind")
    kw = dict(sigma_position=sigma_position, sigma_orientation=sigma_orientation)
    ref = identify(robot, datasets[0], solver=solver, max_steps=max_steps, rtol=rtol, atol=atol, **kw)
    device = datasets[0].device
    idx = np.asarray(ref.info["estimated_index"], int)
    x0 = jnp.asarray(ref.a_full)
    w = residual_weights(device, sigma_position, sigma_orientation)
    qs = np.stack([d.q for d in datasets])
    ys = np.stack([d.y for d in datasets])
    # the same O(1) residual normalisation as `identify`, per robot
    ws = np.stack([np.asarray(w / jnp.maximum(_rms_residual(robot, device, x0, jnp.asarray(q), jnp.asarray(y), w), 1e-12))
                   for q, y in zip(qs, ys)])
    mask = np.zeros(len(ref.names))
    mask[idx] = 1.0
    shared = dict(x0=x0, a_ref=x0, mask=jnp.asarray(mask), mu=jnp.float64(0.0),
                  x_scale=jnp.asarray(_x_scale(tuple(robot.units) + tuple(device.units))),
                  lb=jnp.full(len(mask), -jnp.inf), ub=jnp.full(len(mask), jnp.inf))
    n_dev = 1 if devices is not None and len(devices) <= 1 else len(jax.devices() if devices is None else devices)
    pad = (-len(datasets)) % n_dev
    batched = {"q": np.concatenate([qs, qs[:pad]]), "y": np.concatenate([ys, ys[:pad]]), "w": np.concatenate([ws, ws[:pad]])}
    cfg = dict(robot=robot, device=device, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol)
    fn = functools.partial(_solve_fleet, **cfg)
    t1 = time.perf_counter()
    x, ok, steps, _ = over_devices(fn, batched, shared, devices)
    run_s = time.perf_counter() - t1
    x, ok, steps = x[: len(datasets)], ok[: len(datasets)], steps[: len(datasets)]
    x = np.where(mask > 0, x, np.asarray(x0))
    unit_w = residual_weights(device, 1.0, 1.0)
    rms = []
    for a, q, y in zip(x, qs, ys):
        pe, _ = device.split_errors(residuals(robot, device, jnp.asarray(a), jnp.asarray(q), jnp.asarray(y), unit_w))
        rms.append(float(np.sqrt(np.mean(np.asarray(pe) ** 2)) * 1e3))
    return FleetResult(ref.names, x, ok, steps, np.array(rms), ref.estimated,
                       {"reference_fit_s": t1 - t0, "fleet_s (compile + run)": run_s, "devices": n_dev})


__all__ = ["FleetResult", "identify_fleet", "over_devices"]
