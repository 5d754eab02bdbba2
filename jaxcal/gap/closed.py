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
thermal        p' = p0 + (1 + kappa * tau) (p - p0): every length of the mechanism scaled by the same
               factor is a similarity of the closed mechanism (angles and hence the closure are
               unchanged), so the tool point scales about the base origin p0 exactly
device effects (device_scale, device_bias, drift) act on the reading as for open chains.

Not in the closed-loop library: link_bending (its load model needs the internal forces of the
loop). Effects the geometry or the device frame absorb exactly (a constant device offset; an
encoder gain where the model has a joint gain) are reported as not separable by `diagnose`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.gap import effects as fx
from jaxcal.measure.devices import Device

CLOSED_EFFECTS = tuple(e for e in fx.EFFECTS if e != "link_bending")
PLATFORM_MASS = 1.0  # kg at the tool point: the default mass model of the compliance effect


@functools.lru_cache(maxsize=32)
def closed_model(robot, device: Device) -> fx.GapModel:
    """The effect layout of a closed-loop robot: the open-chain layout over the actuated joints
    (robot.joint_names) without the link_bending parameters."""
    full = fx._cached_model(robot, device)
    keep = [i for i, e in enumerate(full.effect_of) if e in CLOSED_EFFECTS]
    return dataclasses.replace(full, effect_names=tuple(full.effect_names[i] for i in keep),
                               effect_of=tuple(full.effect_of[i] for i in keep),
                               joint_of=tuple(full.joint_of[i] for i in keep))


def _tool_point(robot, q):
    from jaxcal.forward import forward

    return forward(robot, robot.nominal, q).p


def platform_load(robot, q):
    """Gravity load tau (n,) on each actuated joint, kg m: tau_j = m (d p_tool / d q_j) . g_hat on the
    nominal geometry (virtual work; the default one-mass model at the tool point)."""
    J = jax.jacfwd(functools.partial(_tool_point, robot))(jax.lax.stop_gradient(q))  # (3, n)
    return PLATFORM_MASS * (jnp.asarray(fx.G_HAT) @ J)


def actuator_offsets(model: fx.GapModel, e, q, cov):
    """dq (n,) added to the actuator readings: gear, backlash, gain, coupling and compliance."""
    comp = fx._effect_block(model, e, "compliance")[:, 0]
    return fx.joint_offsets(model, e, q, cov) + comp * platform_load(model.robot, q)


def tool_pose(model: fx.GapModel, x, q, cov):
    """Tool pose (R, p) of the closed mechanism with the robot-side effects, for one sample."""
    from jaxcal.forward import forward

    robot = model.robot
    a, e = x[:robot.n_params], x[model.n_geometry:]
    pose = forward(robot, a, q + actuator_offsets(model, e, q, cov))
    p0 = robot.base.p if robot.base is not None else jnp.zeros(3)
    p = p0 + (1.0 + fx._global(model, e, "thermal")[0] * cov[1]) * (pose.p - p0)
    return pose.R, p


def loads_and_tips(model: fx.GapModel, x, q):
    """Gravity load on each actuator (N, n; kg m) and the tool point (N, 3) for `where`."""
    from jaxcal.forward import forward

    a = x[:model.robot.n_params]
    return jax.vmap(functools.partial(platform_load, model.robot))(q), forward(model.robot, a, q).p


def delta_workspace(n: int, seed: int = 0, center=(0.0, 0.0, -1.0), size: float = 0.4) -> np.ndarray:
    """Actuator settings (n, 3) of the nominal Delta reaching points drawn uniformly in a cube of edge
    `size` (m) around `center` (the 400 mm measurement cube of seed 004 §4.4.2), by the inverse solution."""
    from jaxcal.closure import delta as dl

    P = np.asarray(center, float) + size * (np.random.default_rng(seed).random((n, 3)) - 0.5)
    theta, ok = jax.jit(jax.vmap(dl.inverse))(jnp.asarray(P))
    if not bool(jnp.all(ok)):
        raise ValueError(f"delta_workspace: {int(np.sum(~np.asarray(ok)))} points of the cube are out of reach")
    return np.asarray(theta)


__all__ = ["CLOSED_EFFECTS", "PLATFORM_MASS", "actuator_offsets", "closed_model", "delta_workspace", "loads_and_tips",
           "platform_load", "tool_pose"]
