"""The gap model as the calibration core's residual model, and the kernels the diagnosis evaluates.

`GapResiduals` hands a `GapModel` (x = [robot, device, effect parameters], per-sample covariates) to the
calibration core (`jaxcal.fit.core.Problem(model=...)`): the diagnosis' refits run on the core's solve path
(`core.solve_batch` with the folds' priors and weight masks batched, `core.stacked_basis`). Samples are
padded to a bucket size with weight 0 (`padded_size`), so datasets of similar size share compiled code.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.autodiff import value_and_jacfwd
from jaxcal.gap import closed
from jaxcal.gap.effects import carried, gravity_loads, joint_axes, payload_loads, read_batch, residuals, tip_bodies
from jaxcal.gap.model import GapModel
from jaxcal.kin.model import frames_single, joint_variables

SIZE_BUCKETS = (96, 192, 320)  # padded sample counts; beyond 320, multiples of 128


@dataclasses.dataclass(frozen=True)
class GapResiduals:
    """A `GapModel` as the calibration core's residual model (names, units, priority, x_scale, residuals).
    Hashes by its model (models are cached per robot and device, so compiled solvers are shared)."""

    model: GapModel

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    @property
    def units(self) -> tuple[str, ...]:
        m = self.model
        return tuple(m.robot.units) + tuple(m.device.units) + ("effect",) * len(m.effect_names)

    @property
    def priority(self) -> np.ndarray:
        m = self.model
        return np.concatenate([m.robot.priority, m.device.priority, np.zeros(len(m.effect_names))])

    def x_scale(self) -> np.ndarray:
        return self.model.x_scale()

    @property
    def jacobian_mode(self) -> str:
        """Reverse mode sample by sample for open chains (`core.data_residual_and_jacobian`), forward through closures."""
        return "reverse" if self.model.robot.closure is None else "forward"

    def residuals(self, x, q, y, cov, w):
        """w * (y - read(x, q, c)) (N, m) with every effect at its value in x (`jaxcal.gap.effects.residuals`)."""
        return residuals(self.model, x, q, y, cov, w)


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
    """Length of the refit's unknown vector z (`core.stacked_basis`): the columns rounded up to a multiple of 8
    (fewer compiles)."""
    return int(np.ceil(max(n_columns, 1) / 8)) * 8


@functools.partial(jax.jit, static_argnames=("model",))
def jacobians(xs, q, y, cov, w, *, model):
    """Residuals (B, N*m) and their Jacobians (B, N*m, P) at each xs[b] (all samples, weights w)."""

    def one(x):
        f = lambda v: residuals(model, v, q, y, cov, w).reshape(-1)  # noqa: E731
        return value_and_jacfwd(f, x)

    return jax.vmap(one)(xs)


@functools.partial(jax.jit, static_argnames=("model",))
def predict(x, q, cov, *, model):
    """Predicted readings (N, ...) at x."""
    return read_batch(model, x, q, cov)


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
    """(|M_j|, |P_j|), each (N, n; kg m): norms of the gravity moment of the robot's masses (compliance and bending
    act on it) and of 1 kg at the tool point (payload) about each joint, for every sample."""
    if model.robot.closure is not None:  # closed loops: compliance acts on the actuator load tau_j (jaxcal/gap/closed.py)
        tau = jnp.abs(loads_and_tips(x, q, None, model=model)[0])
        return tau, tau
    a = x[:model.robot.n_params]

    def one(qi):
        F = frames_single(model.robot, a, joint_variables(model.robot, a, qi))
        o, _ = joint_axes(model, F)
        tips = tip_bodies(model.robot)
        payload = jnp.einsum("jk,kji->ji", jnp.asarray(carried(model, tips)),
                             jax.vmap(payload_loads, (0, None))(F.p[np.array(tips)], o))
        return jnp.linalg.norm(gravity_loads(model, F, o), axis=1), jnp.linalg.norm(payload, axis=1)

    return jax.vmap(one)(q)


@functools.partial(jax.jit, static_argnames=("model",))
def residual_batch(xs, q, y, cov, w, *, model):
    """Residuals (B, N, m) at each xs[b]."""
    return jax.vmap(lambda x: residuals(model, x, q, y, cov, w))(xs)
