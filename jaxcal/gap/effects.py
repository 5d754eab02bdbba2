"""The effect library's prediction: differentiable extensions of the forward model (issue 7, DESIGN "gap").

The effects are `jaxcal.gap.effect.Effect` objects (one module each in `jaxcal/gap/library/`); the
parameter layout is `jaxcal.gap.model.GapModel`. This module evaluates the tool pose of an open chain
with the effects at the places they act (`tool_pose`; closed loops: `jaxcal.gap.closed`) and the
device reading (`read`). The built-in library, per sample, with motor readings q and covariates
c = (time, thermal driver, direction per joint):

joint-space effects (added to the motor reading before the joint model, seed 001 eq 4):
  gear         dq_j = s1 sin q_j + c1 cos q_j + s2 sin 2q_j + c2 cos 2q_j   (revolute joints)
  backlash     dq_j = b_j * direction_j                                     (direction = +-1)
  encoder_gain dq_j = g_j * q_j
  coupling     dq_j = k_j * q_{j-1}                                         (off-diagonal Cm)
gravity effects (first-order rotations about the joint axis (o_j, z_j) of everything distal):
  load M_j = sum_{bodies k distal to j} (c_k - o_j) x (m_k * g_hat) (kg m; g_hat = -z of the robot
  base frame, so the gravity torque is 9.81 M_j N m), with the mass m_k and centre of mass c_k of
  each body from the URDF inertials (`robot.extras["inertia"]`) when the robot has them, else the
  default mass model: 1 kg at each body origin (c_k = p_k)
  compliance   dphi_j = c_j (z_j . M_j) z_j                                 (revolute joints)
  link_bending dphi_j = b_j (M_j - (z_j . M_j) z_j)      (bending perpendicular to the joint axis)
  payload      dphi_j = c_j (z_j . P_j) z_j, P_j = (p - o_j) x g_hat: a point mass at the tool point p
  tip: p' = p + sum_j dphi_j x (p - o_j),  R' = exp(sum_j dphi_j) R
thermal        p' = p0 + (1 + kappa * tau) (p' - p0) + tau v: expansion about an unknown centre c, with
               v = kappa (p0 - c), p0 the robot base origin, tau the thermal driver (standardised
               temperature, else standardised time)
device effects on the reading's position y (device frame; their changes add, each from the unchanged y):
  device_scale y' = (1 + s) * y (per axis)
  device_bias  y' = y + b + rho * y / |y|   (constant offset b: absorbed by the device frame;
               rho: range offset of a laser tracker)
  drift        y' = y + t (v + w x y), R' = exp(t w) R   (t standardised time)
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.gap import closed
from jaxcal.gap.effect import EFFECT_SCALE, get_effect, registered_effects
from jaxcal.gap.model import G_HAT, GapModel, gap_model, joint_offsets, params_of, reading_effects, tool_transforms
from jaxcal.kin.convention import joint_line
from jaxcal.kin.model import frames_single, joint_variables
from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import exp_so3

# The built-in library (the registry at import; `registered_effects()` includes effects added later).
EFFECTS = registered_effects()
JOINT_EFFECTS = tuple(e for e in EFFECTS if get_effect(e).per_joint)
GLOBAL_EFFECTS = tuple(e for e in EFFECTS if not get_effect(e).per_joint)
# Covariate an effect needs to be a candidate (None: always a candidate).
NEEDS = {e: get_effect(e).needs for e in EFFECTS if get_effect(e).needs is not None}


def joint_axes(model: GapModel, F):
    """(o_j, z_j): a point on each joint axis and its direction in the world, from the body frames F
    (`kin.convention.joint_line`: the parent's axis for standard DH, the parent's origin for PRY modules)."""
    robot = model.robot
    root_p = robot.base.p if robot.base is not None else jnp.zeros(3)
    root_R = robot.base.R if robot.base is not None else jnp.eye(3)
    pts, dirs = [], []
    for b in model.joint_body:
        body = robot.bodies[b]
        R_par, p_par = (root_R, root_p) if body.parent < 0 else (F.R[body.parent], F.p[body.parent])
        o, z = joint_line(body.conv, body.kind, F.R[b], F.p[b], R_par, p_par)
        pts.append(o)
        dirs.append(z)
    return jnp.stack(pts), jnp.stack(dirs)


def gravity_loads(model: GapModel, F, o):
    """Gravity moment M_j (n, 3; kg m) about each joint axis point o_j: sum over the distal bodies k of
    (c_k - o_j) x (m_k g_hat); URDF masses and centres of mass when known, else 1 kg at each body origin."""
    g = jnp.asarray(G_HAT)
    if model.body_mass:
        mass = jnp.asarray(model.body_mass)
        centres = F.p + jnp.einsum("bij,bj->bi", F.R, jnp.asarray(model.body_com))
    else:
        mass, centres = jnp.ones(len(model.robot.bodies)), F.p
    loads = []
    for j, bodies in enumerate(model.distal):
        k = jnp.asarray(bodies)
        loads.append(jnp.sum(mass[k, None] * jnp.cross(centres[k] - o[j], g), axis=0))
    return jnp.stack(loads)


def payload_loads(p, o):
    """Gravity moment P_j (n, 3; kg m per kg) of a unit mass at the tool point p about each joint axis point o_j:
    (p - o_j) x g_hat."""
    return jnp.cross(p - o, jnp.asarray(G_HAT))


def tip_bodies(robot) -> tuple[int, ...]:
    """Body index of each tool frame the robot is read at: `robot.tips` for a tree read at several bodies, else `tip`."""
    return tuple(int(t) % len(robot.bodies) for t in (robot.tips or (robot.tip,)))


def carried(model: GapModel, tips: tuple[int, ...]) -> np.ndarray:
    """(n_joints, K) 1.0 where joint j carries tip k (the tip's body is distal to the joint), else 0.0."""
    return np.array([[1.0 if t in distal else 0.0 for t in tips] for distal in model.distal])


def open_tool_pose(model: GapModel, x, q, cov):
    """Tip pose (R, p) of an open chain or tree with the robot-side effects, for one sample: joint offsets, then
    the kinematics, then the gravity rotations dphi_j about the joint axes (o_j, z_j) of everything distal,
    p_k' = p_k + sum_{j carrying k} dphi_j x (p_k - o_j), R_k' = exp(sum_{j carrying k} dphi_j) R_k, then the tool
    transforms. A payload sits at every tip; joint j feels the payloads of the tips it carries. A tree read at
    several bodies returns the stacked (K, 3, 3), (K, 3)."""
    robot = model.robot
    a, e = x[:robot.n_params], x[model.n_geometry:]
    qm = q + joint_offsets(model, e, q, cov)
    F = frames_single(robot, a, joint_variables(robot, a, qm))
    tips = tip_bodies(robot)
    R, p = F.R[np.array(tips)], F.p[np.array(tips)]
    gravity, payload = model.acting_on("gravity"), model.acting_on("payload")
    if gravity or payload:
        o, z = joint_axes(model, F)
        under = jnp.asarray(carried(model, tips))
        dphi = jnp.zeros_like(o)
        if gravity:
            M = gravity_loads(model, F, o)
            dphi = dphi + sum(fx.tool_rotation(params_of(model, e, fx), M, z) for fx in gravity)
        if payload:
            P = jnp.einsum("jk,kji->ji", under, jax.vmap(payload_loads, (0, None))(p, o))
            dphi = dphi + sum(fx.tool_rotation(params_of(model, e, fx), P, z) for fx in payload)
        p = p + jnp.einsum("jk,kji->ki", under, jnp.cross(dphi[None], p[:, None] - o[None]))
        R = jax.vmap(exp_so3)(under.T @ dphi) @ R
    poses = [tool_transforms(model, e, R[k], p[k], cov) for k in range(len(tips))]
    if not robot.tips:
        return poses[0]
    return jnp.stack([r for r, _ in poses]), jnp.stack([t for _, t in poses])


def tool_pose(model: GapModel, x, q, cov, load=None):
    """Tip pose (R, p) in the robot base frame with the robot-side effects, open chain or closed loop (load: a
    closed loop's actuator load, `closed.tool_pose`)."""
    if model.robot.closure is not None:
        return closed.tool_pose(model, x, q, cov, load)
    return open_tool_pose(model, x, q, cov)


def read(model: GapModel, x, q, cov, load=None):
    """Predicted device reading of one sample with every effect at the values in x."""
    nr, ng = model.robot.n_params, model.n_geometry
    R, p = tool_pose(model, x, q, cov, load)
    return reading_effects(model, x[ng:], model.device.read(Pose(R, p), x[nr:ng]), cov)


def read_batch(model: GapModel, x, q, cov):
    """`read` of every sample (N, ...); a closed loop's actuator loads computed for the batch first
    (`closed.actuator_loads`: they do not depend on x)."""
    loads = closed.actuator_loads(model, q) if model.robot.closure is not None else None
    if loads is None:
        return jax.vmap(functools.partial(read, model, x))(q, cov)
    return jax.vmap(functools.partial(read, model, x))(q, cov, loads)


def residuals(model: GapModel, x, q, y, cov, w):
    """Weighted residuals (N, m): w * (measured - predicted), all samples."""
    return jax.vmap(model.device.residual)(read_batch(model, x, q, cov), y) * w


__all__ = ["EFFECTS", "EFFECT_SCALE", "GLOBAL_EFFECTS", "JOINT_EFFECTS", "NEEDS", "GapModel", "gap_model", "gravity_loads",
           "joint_axes", "open_tool_pose", "payload_loads", "read", "read_batch", "residuals", "tool_pose"]
