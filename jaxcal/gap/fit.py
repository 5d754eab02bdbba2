"""Joint identification of geometry, device frame and effects for the gap diagnosis.

The stacked residual generalises `jaxcal.fit.core.stacked` with per-sample covariates and
effect parameters: data rows w * (y - read(x, q, c)) with x = x_ref + S z (S selects the estimated
parameters at their typical size, so the others stay at x_ref), and Tikhonov rows sqrt(mu) z that
hold the estimated geometry near x_ref (seed 004 eq 3.12, as `jaxcal.realdata`'s "prior").
Samples are padded to a bucket size with
weight 0 and folds are weight masks, so one compiled LM (optimistix, identify's solver) serves
every candidate, fold and dataset of similar size; the folds are solved in one vmapped call.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxcal.fit.core import make_solver
from jaxcal.gap import closed
from jaxcal.gap.effects import gravity_loads, joint_axes, read, residuals
from jaxcal.gap.model import GapModel
from jaxcal.kin.model import frames_single, joint_variables

SIZE_BUCKETS = (96, 192, 320)  # padded sample counts; beyond 320, multiples of 128
RTOL, ATOL = 1e-5, 1e-7  # LM tolerances on the cost and on the step z (z in units of the typical parameter size)


def padded_size(n: int) -> int:
    """Samples are padded (weight 0) to a bucket size so datasets of similar size share compiled code."""
    for b in SIZE_BUCKETS:
        if n <= b:
            return b
    return int(np.ceil(n / 128)) * 128


def covariate_matrix(model: GapModel, covariates: dict, n: int):
    """(N, 2 + n_joints): standardised time, thermal driver (temperature, else time), direction per joint.

    Returns the matrix and the covariates present ({"time", "thermal", "direction"} subset).
    """
    nj = model.robot.n_inputs
    C = np.zeros((n, 2 + nj))
    present = set()

    def standard(v, name):
        v = np.asarray(v, float).reshape(-1)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"covariate {name!r}: non-finite values in sample(s) {np.flatnonzero(~np.isfinite(v))[:10].tolist()}")
        s = np.std(v)
        return (v - np.mean(v)) / s if s > 0 else None

    if "time" in covariates:
        t = standard(covariates["time"], "time")
        if t is not None:
            C[:, 0], C[:, 1] = t, t
            present |= {"time", "thermal"}
    if "temperature" in covariates:
        c = standard(covariates["temperature"], "temperature")
        if c is not None:
            C[:, 1] = c
            present.add("thermal")
    if "direction" in covariates:
        d = np.asarray(covariates["direction"], float)
        d = np.repeat(d.reshape(-1, 1), nj, axis=1) if d.ndim == 1 else d
        if d.shape != (n, nj):
            raise ValueError(f"covariate 'direction' must have shape (N,) or (N, {nj}), got {np.shape(covariates['direction'])}")
        if not np.all(np.isfinite(d)):
            raise ValueError("covariate 'direction': non-finite values")
        C[:, 2:] = np.sign(d)
        present.add("direction")
    return C, present


def active_size(n_columns: int) -> int:
    """Length of the estimated vector z: the columns rounded up to a multiple of 8 (fewer compiles)."""
    return int(np.ceil(max(n_columns, 1) / 8)) * 8


def selection(cols, n_params: int, scale, K: int) -> np.ndarray:
    """(P, K) matrix S with x = x_ref + S z: column i of S picks parameter cols[i] at its typical size
    (columns beyond len(cols) are zero, so one K, hence one compiled solver, serves every stage)."""
    S = np.zeros((n_params, K))
    S[np.asarray(cols, int), np.arange(len(cols))] = np.asarray(scale)[np.asarray(cols, int)]
    return S


def _data_rows(model, z, a):
    return residuals(model, a["ref"] + a["S"] @ z, a["q"], a["y"], a["cov"], a["w"]).reshape(-1)


def _rows_with_prior(model, z, a):
    return jnp.concatenate([_data_rows(model, z, a), jnp.sqrt(a["mu"]) * z])


_AXES = {"ref": 0, "w": 0, "S": None, "mu": None, "q": None, "y": None, "cov": None}


@functools.partial(jax.jit, static_argnames=("model", "max_steps"))
def solve_folds(x_refs, z_starts, args, *, model, max_steps=100):
    """LM on z, x = x_ref + S z, for each fold b: reference x_refs[b], start z_starts[b], weights args["w"][b].

    Minimises ||rows(z)||^2 / s_b^2 + sum_i mu_i z_i^2, with s_b^2 the mean square data row at the
    reference (so mu_i = 1 makes a departure of one typical size cost as much as one reading at the
    reference's RMS residual). Returns (x, ok, steps). Only the K selected columns are differentiated."""

    def one(x_ref, z0, a):
        a = dict(a, ref=x_ref)
        r_ref = _data_rows(model, jnp.zeros_like(z0), a)
        a = dict(a, w=a["w"] / jnp.maximum(jnp.sqrt(jnp.sum(r_ref**2) / jnp.maximum(jnp.sum(a["w"] > 0), 1)), 1e-12))
        fn = functools.partial(_rows_with_prior, model)
        sol = optx.least_squares(fn, make_solver("lm", RTOL, ATOL), z0, a, max_steps=max_steps, throw=False)
        return x_ref + a["S"] @ sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    return jax.vmap(one, (0, 0, _AXES))(x_refs, z_starts, args)


@functools.partial(jax.jit, static_argnames=("model",))
def jacobians(xs, q, y, cov, w, *, model):
    """Residuals (B, N*m) and their Jacobians (B, N*m, P) at each xs[b] (all samples, weights w)."""

    def one(x):
        f = lambda v: residuals(model, v, q, y, cov, w).reshape(-1)  # noqa: E731
        return f(x), jax.jacfwd(f)(x)

    return jax.vmap(one)(xs)


@functools.partial(jax.jit, static_argnames=("model",))
def predict(x, q, cov, *, model):
    """Predicted readings (N, ...) at x."""
    return jax.vmap(functools.partial(read, model, x))(q, cov)


@functools.partial(jax.jit, static_argnames=("model",))
def loads_and_tips(x, q, cov, *, model):
    """Gravity load about each joint axis (N, n; kg m, the model's masses) and the tip position (N, 3)."""
    if model.robot.closure is not None:
        return closed.loads_and_tips(model, x, q)
    a = x[:model.robot.n_params]

    def one(qi):
        F = frames_single(model.robot, a, joint_variables(model.robot, a, qi))
        o, z = joint_axes(model, F)
        return jnp.sum(gravity_loads(model, F, o) * z, axis=1), F.p[model.robot.tip]

    return jax.vmap(one)(q)


@functools.partial(jax.jit, static_argnames=("model",))
def moment_norms(x, q, *, model):
    """|M_j| (N, n; kg m): norm of the gravity moment about each joint of every sample (compliance and bending act on it)."""
    if model.robot.closure is not None:  # closed loops: compliance acts on the actuator load tau_j (jaxcal/gap/closed.py)
        return jnp.abs(loads_and_tips(x, q, None, model=model)[0])
    a = x[:model.robot.n_params]

    def one(qi):
        F = frames_single(model.robot, a, joint_variables(model.robot, a, qi))
        o, _ = joint_axes(model, F)
        return jnp.linalg.norm(gravity_loads(model, F, o), axis=1)

    return jax.vmap(one)(q)


@functools.partial(jax.jit, static_argnames=("model",))
def residual_batch(xs, q, y, cov, w, *, model):
    """Residuals (B, N, m) at each xs[b]."""
    return jax.vmap(lambda x: residuals(model, x, q, y, cov, w))(xs)
