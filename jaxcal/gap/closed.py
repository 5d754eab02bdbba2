"""The gap effect library for closed-loop robots (issue 7 part c): the Delta and other mechanisms
whose tool pose comes from a loop closure (`jaxcal.closure`; the Delta's fast exact closure in
`jaxcal.closure.delta`).

Every effect is a differentiable extension of the closed-loop forward `jc.forward(robot, a, q)`
(closure inside; derivatives by the implicit function theorem), with the parameter layout and the
names of the open-chain library (`jaxcal.gap.effects`), so `jc.gap.diagnose` serves both. Per
sample, with actuator readings q and covariates c = (time, thermal driver, direction per joint):

actuated-joint effects (added to the actuator reading before the closure, seed 001 eq 4):
  gear         dq_j = s1 sin q_j + c1 cos q_j + s2 sin 2q_j + c2 cos 2q_j   (revolute actuators)
  backlash     dq_j = b_j * direction_j
  encoder_gain dq_j = g_j * q_j
  coupling     dq_j = k_j * q_{j-1}
  compliance   dq_j = c_j * tau_j(q), tau_j = m (d p_tool / d q_j) . g_hat   (revolute actuators)
               the gravity load on actuator j by virtual work. Default mass model: one point mass
               m = 1 kg (load in kg m, as the open-chain library) at the tool point (the Delta's
               nacelle centre: the platform and its payload), gravity -z of the robot base frame;
               the rods and arms are taken as massless. tau is evaluated on the nominal geometry
               (the first-order load; it does not depend on the parameters being fitted).
thermal        p' = p0 + (1 + kappa * tau) (p - p0) + tau v: every length of the mechanism scaled by the same
               factor is a similarity of the closed mechanism (angles and hence the closure are
               unchanged), so the tool point scales about the base origin p0 exactly; v moves the
               centre of the expansion (`jaxcal.gap.library.thermal`)
device effects (device_scale, device_bias, drift) act on the reading as for open chains.

The layout is `jaxcal.gap.model.gap_model`'s with the effects marked `closed_loop`; the hooks are the
open chain's ("joint", "tool", "reading") plus "actuator_load" (compliance). Not in the closed-loop
library: link_bending (its load model needs the internal forces of the
loop). Effects the geometry or the device frame absorb exactly (a constant device offset; an
encoder gain where the model has a joint gain) are reported as not separable by `diagnose`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.closure import delta as dl
from jaxcal.forward import forward
from jaxcal.gap.effect import get_effect, registered_effects
from jaxcal.gap.model import G_HAT, GapModel, joint_offsets, params_of, tool_transforms

# The built-in closed-loop library (the registry at import).
CLOSED_EFFECTS = tuple(e for e in registered_effects() if get_effect(e).closed_loop)
PLATFORM_MASS = 1.0  # kg at the tool point: the default mass model of the compliance effect


def _tool_point(robot, q):
    return forward(robot, robot.nominal, q).p


def platform_load(robot, q):
    """Gravity load tau (n,) on each actuated joint, kg m: tau_j = m (d p_tool / d q_j) . g_hat on the
    nominal geometry (virtual work; the default one-mass model at the tool point)."""
    J = jax.jacfwd(functools.partial(_tool_point, robot))(jax.lax.stop_gradient(q))  # (3, n)
    return PLATFORM_MASS * (jnp.asarray(G_HAT) @ J)


def platform_loads(robot, q):
    """`platform_load` of a batch of actuator settings q (N, n): the nominal closure solved once for the batch
    (`Closure.presolve`), then each sample's d p_tool / d q through the implicit step of
    `Closure.forward_presolved` (forward mode, n tangents). Sample by sample, `platform_load` solves the closure
    inside each sample's derivative: Delta, 192 samples, 18.5 ms a batch."""
    q = jax.lax.stop_gradient(jnp.asarray(q, jnp.float64))
    a, closure = robot.nominal, robot.closure
    pre = closure.presolve(robot, a, q)

    def one(qi, pi):
        def tool_point(qq):
            return closure.forward_presolved(robot, a, qq[None], jax.tree_util.tree_map(lambda v: v[None], pi)).p[0]

        return PLATFORM_MASS * (jnp.asarray(G_HAT) @ jax.jacfwd(tool_point)(qi))

    return jax.vmap(one)(q, pre)


def actuator_offsets(model: GapModel, e, q, cov, tau=None):
    """dq (n,) added to the actuator readings: the "joint" effects, then the "actuator_load" ones on tau (the
    sample's `platform_load`; None: computed here)."""
    dq = joint_offsets(model, e, q, cov)
    loaded = model.acting_on("actuator_load")
    if loaded:
        tau = platform_load(model.robot, q) if tau is None else tau
        for fx in loaded:
            dq = dq + fx.actuator_offset(params_of(model, e, fx), tau)
    return dq


def tool_pose(model: GapModel, x, q, cov, tau=None):
    """Tool pose (R, p) of the closed mechanism with the robot-side effects, for one sample (tau: its actuator
    load, as in `actuator_offsets`)."""
    robot = model.robot
    a, e = x[:robot.n_params], x[model.n_geometry:]
    pose = forward(robot, a, q + actuator_offsets(model, e, q, cov, tau))
    return tool_transforms(model, e, pose.R, pose.p, cov)


def actuator_loads(model: GapModel, q):
    """The actuator loads (N, n) the model's "actuator_load" effects need for samples q (N, n) (`platform_loads`),
    or None when it has none."""
    return platform_loads(model.robot, q) if model.acting_on("actuator_load") else None


def loads_and_tips(model: GapModel, x, q):
    """Gravity load on each actuator (N, n; kg m) and the tool point (N, 3) for `where`."""
    a = x[:model.robot.n_params]
    return platform_loads(model.robot, q), forward(model.robot, a, q).p


def delta_workspace(n: int, seed: int = 0, center=(0.0, 0.0, -1.0), size: float = 0.4) -> np.ndarray:
    """Actuator settings (n, 3) of the nominal Delta reaching points drawn uniformly in a cube of edge
    `size` (m) around `center` (the 400 mm measurement cube of seed 004 §4.4.2), by the inverse solution."""
    P = np.asarray(center, float) + size * (np.random.default_rng(seed).random((n, 3)) - 0.5)
    theta, ok = jax.jit(jax.vmap(dl.inverse))(jnp.asarray(P))
    if not bool(jnp.all(ok)):
        raise ValueError(f"delta_workspace: {int(np.sum(~np.asarray(ok)))} points of the cube are out of reach")
    return np.asarray(theta)


__all__ = ["CLOSED_EFFECTS", "PLATFORM_MASS", "actuator_loads", "actuator_offsets", "delta_workspace", "loads_and_tips",
           "platform_load", "platform_loads", "tool_pose"]
