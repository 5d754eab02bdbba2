"""The effect library: differentiable extensions of the forward model (issue 7, DESIGN "gap").

One `GapModel` per (robot, device) holds every effect's parameters in one vector appended to the
robot and device parameters, x = [a_robot, d_device, e_effects]. A candidate switches effects on
by a mask (the others stay pinned at zero), so one compiled solver serves every candidate, every
joint-restricted variant and every fold.

Per sample, with motor readings q, covariates c = (time, thermal driver, direction per joint):

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
  tip: p' = p + sum_j dphi_j x (p - o_j),  R' = exp(sum_j dphi_j) R
thermal        p' = p0 + (1 + kappa * tau) (p' - p0), p0 the robot base origin, tau the thermal
               driver (standardised temperature, else standardised time)
device effects on the reading's position y (device frame):
  device_scale y' = (1 + s) * y (per axis)
  device_bias  y' = y + b + rho * y / |y|   (constant offset b: absorbed by the device frame;
               rho: range offset of a laser tracker)
  drift        y' = y + t (v + w x y), R' = exp(t w) R   (t standardised time)
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.model import Robot, frames_single, joint_variables
from jaxcal.kin.rotations import exp_so3
from jaxcal.measure.devices import Device

EFFECTS = ("compliance", "gear", "backlash", "encoder_gain", "coupling", "thermal", "drift", "device_scale",
           "device_bias", "link_bending")
JOINT_EFFECTS = ("compliance", "gear", "backlash", "encoder_gain", "coupling", "link_bending")
GLOBAL_EFFECTS = ("thermal", "drift", "device_scale", "device_bias")
# Covariate an effect needs to be a candidate (None: always a candidate).
NEEDS = {"backlash": "direction", "thermal": "thermal", "drift": "time"}
_GEAR_TERMS = ("s1", "c1", "s2", "c2")
_DRIFT_TERMS = ("vx", "vy", "vz", "wx", "wy", "wz")
EFFECT_SCALE = 1e-3  # typical size of an effect parameter (rad, m, or relative)
G_HAT = np.array([0.0, 0.0, -1.0])  # gravity direction in the robot base frame (load in kg m)


def _is_revolute(body) -> bool:
    return body.conv.is_revolute(body.kind)


@dataclasses.dataclass(frozen=True, eq=False)
class GapModel:
    """Robot + device + effect parameter layout. Hashes by identity (a static jit argument)."""

    robot: Robot
    device: Device
    effect_names: tuple[str, ...]  # names of the effect parameters, "gap.<effect>[.<joint>][.<term>]"
    effect_of: tuple[str, ...]  # effect of each effect parameter
    joint_of: tuple[int, ...]  # joint index of each effect parameter, -1 for global ones
    joint_body: tuple[int, ...]  # body consuming each joint input
    revolute: tuple[bool, ...]
    distal: tuple[tuple[int, ...], ...]  # bodies distal to each joint (their masses load the joint)
    body_mass: tuple[float, ...] = ()  # kg per body (URDF inertials); () = the default mass model
    body_com: tuple[tuple[float, float, float], ...] = ()  # centre of mass per body, in the body frame (m)

    @property
    def mass_model(self) -> str:
        """Which masses load the gravity effects (say it in reports)."""
        if self.body_mass:
            return f"URDF inertials ({sum(self.body_mass):.3g} kg on {sum(m > 0 for m in self.body_mass)} bodies)"
        return "default: 1 kg at each body origin"

    @property
    def n_geometry(self) -> int:
        return self.robot.n_params + self.device.n_params

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.robot.names) + tuple(self.device.names) + self.effect_names

    @property
    def n_params(self) -> int:
        return len(self.names)

    def index(self, effect: str, joints=None) -> np.ndarray:
        """Indices into x of an effect's parameters (restricted to `joints` for joint effects)."""
        eff = np.array(self.effect_of)
        jnt = np.array(self.joint_of)
        sel = eff == effect
        if joints is not None:
            sel &= np.isin(jnt, list(joints))
        return self.n_geometry + np.flatnonzero(sel)

    def joints_with(self, effect: str) -> tuple[int, ...]:
        return tuple(sorted({j for e, j in zip(self.effect_of, self.joint_of) if e == effect and j >= 0}))

    def nominal(self) -> np.ndarray:
        return np.concatenate([self.robot.nominal_np, self.device.nominal_np, np.zeros(len(self.effect_names))])

    def x_scale(self) -> np.ndarray:
        units = tuple(self.robot.units) + tuple(self.device.units)
        geo = [1.0 if u in ("gain", "scale") else 0.01 for u in units]
        return np.array(geo + [EFFECT_SCALE] * len(self.effect_names))


def _descendants(robot: Robot, b: int) -> tuple[int, ...]:
    out = []
    for k, body in enumerate(robot.bodies):
        i = k
        while i >= 0:
            if i == b:
                out.append(k)
                break
            i = robot.bodies[i].parent
    return tuple(out)


@functools.lru_cache(maxsize=64)
def _cached_model(robot: Robot, device: Device) -> GapModel:
    n = robot.n_inputs
    joint_body = []
    for j in range(n):
        owners = [b for b, body in enumerate(robot.bodies) if j in body.inputs]
        if not owners:
            raise ValueError(f"robot {robot.name!r}: joint input {j} is consumed by no body")
        joint_body.append(owners[0])
    revolute = tuple(_is_revolute(robot.bodies[b]) for b in joint_body)
    jn = robot.joint_names
    names, eff, jnt = [], [], []

    def add(name, effect, joint):
        names.append(name)
        eff.append(effect)
        jnt.append(joint)

    for j in range(n):
        if revolute[j]:
            add(f"gap.compliance.{jn[j]}", "compliance", j)
            for t in _GEAR_TERMS:
                add(f"gap.gear.{jn[j]}.{t}", "gear", j)
        add(f"gap.backlash.{jn[j]}", "backlash", j)
        add(f"gap.encoder_gain.{jn[j]}", "encoder_gain", j)
        if j > 0:
            add(f"gap.coupling.{jn[j]}", "coupling", j)
        add(f"gap.link_bending.{jn[j]}", "link_bending", j)
    add("gap.thermal", "thermal", -1)
    for t in _DRIFT_TERMS:
        add(f"gap.drift.{t}", "drift", -1)
    for t in "xyz":
        add(f"gap.device_scale.{t}", "device_scale", -1)
    for t in ("x", "y", "z", "range"):
        add(f"gap.device_bias.{t}", "device_bias", -1)
    distal = tuple(_descendants(robot, b) for b in joint_body)
    mass, com = _urdf_masses(robot)
    return GapModel(robot, device, tuple(names), tuple(eff), tuple(jnt), tuple(joint_body), revolute, distal, mass, com)


def _urdf_masses(robot: Robot):
    """(mass per body, centre of mass per body) from the URDF inertials, or ((), ()) when the robot has none."""
    inertia = robot.extras.get("inertia") if robot.extras else None
    if not inertia or len(inertia) != len(robot.bodies) or sum(b["mass"] for b in inertia) <= 0:
        return (), ()
    return (tuple(float(b["mass"]) for b in inertia),
            tuple(tuple(float(c) for c in np.asarray(b["com"], float)) for b in inertia))


def gap_model(robot: Robot, device: Device) -> GapModel:
    """The effect model of a robot and device (cached, so compiled solvers are shared)."""
    if robot.closure is not None:  # closed-loop robots: the effects act through the closure (jaxcal/gap/closed.py)
        from jaxcal.gap.closed import closed_model

        return closed_model(robot, device)
    return _cached_model(robot, device)


def _block_index(model: GapModel, effect: str) -> np.ndarray:
    """Static (n_joints, k) index of one joint effect's parameters in e; -1 where not applicable."""
    k = 4 if effect == "gear" else 1
    idx = -np.ones((model.robot.n_inputs, k), int)
    seen: dict = {}
    for i, (ef, j) in enumerate(zip(model.effect_of, model.joint_of)):
        if ef == effect:
            idx[j, seen.get(j, 0)] = i
            seen[j] = seen.get(j, 0) + 1
    return idx


def _effect_block(model: GapModel, e, effect: str):
    """Dense (n_joints, k) block of one joint effect's parameters (zeros where not applicable)."""
    return jnp.append(e, 0.0)[jnp.asarray(_block_index(model, effect))]


def _global(model: GapModel, e, effect: str):
    return e[jnp.asarray([i for i, ef in enumerate(model.effect_of) if ef == effect])]


def joint_offsets(model: GapModel, e, q, cov):
    """Joint-space effects: dq (n,) added to the motor readings q (gear, backlash, gain, coupling)."""
    gear = _effect_block(model, e, "gear")
    harm = jnp.stack([jnp.sin(q), jnp.cos(q), jnp.sin(2 * q), jnp.cos(2 * q)], axis=1)
    dq = jnp.sum(gear * harm, axis=1)
    dq = dq + _effect_block(model, e, "backlash")[:, 0] * cov[2:]
    dq = dq + _effect_block(model, e, "encoder_gain")[:, 0] * q
    prev = jnp.concatenate([jnp.zeros(1, q.dtype), q[:-1]])
    return dq + _effect_block(model, e, "coupling")[:, 0] * prev


def joint_axes(model: GapModel, F):
    """(o_j, z_j): a point on each joint axis and its direction, from the body frames F."""
    robot = model.robot
    root = robot.base.p if robot.base is not None else jnp.zeros(3)
    pts, dirs = [], []
    for b in model.joint_body:
        body = robot.bodies[b]
        dirs.append(F.R[b] @ body.conv.joint_axis(body.kind))
        if body.conv.axis_through_parent_origin(body.kind):  # e.g. a PRY module (seed 000 eq 3.45)
            pts.append(root if body.parent < 0 else F.p[body.parent])
        else:
            pts.append(F.p[b])
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


def tool_pose(model: GapModel, x, q, cov):
    """Tip pose (R, p) in the robot base frame with the robot-side effects, for one sample."""
    if model.robot.closure is not None:
        from jaxcal.gap import closed

        return closed.tool_pose(model, x, q, cov)
    robot = model.robot
    nr, ng = robot.n_params, model.n_geometry
    a, e = x[:nr], x[ng:]
    qm = q + joint_offsets(model, e, q, cov)
    F = frames_single(robot, a, joint_variables(robot, a, qm))
    tip = robot.tip
    R, p = F.R[tip], F.p[tip]
    o, z = joint_axes(model, F)
    M = gravity_loads(model, F, o)
    along = jnp.sum(M * z, axis=1)
    comp = _effect_block(model, e, "compliance")[:, 0] * along
    bend = _effect_block(model, e, "link_bending")[:, 0]
    dphi = comp[:, None] * z + bend[:, None] * (M - along[:, None] * z)
    p = p + jnp.sum(jnp.cross(dphi, p - o), axis=0)
    R = exp_so3(jnp.sum(dphi, axis=0)) @ R
    p0 = robot.base.p if robot.base is not None else jnp.zeros(3)
    p = p0 + (1.0 + _global(model, e, "thermal")[0] * cov[1]) * (p - p0)
    return R, p


def read(model: GapModel, x, q, cov):
    """Predicted device reading of one sample with every effect at the values in x."""
    from jaxcal.kin.pose import Pose

    device = model.device
    nr, ng = model.robot.n_params, model.n_geometry
    R, p = tool_pose(model, x, q, cov)
    y = device.read(Pose(R, p), x[nr:ng])
    e = x[ng:]
    t = cov[0]
    scale = _global(model, e, "device_scale")
    bias = _global(model, e, "device_bias")
    drift = _global(model, e, "drift")

    def on_position(v):
        v2 = v * (1.0 + scale) + bias[:3] + bias[3] * v / jnp.sqrt(jnp.sum(v**2) + 1e-12)
        return v2 + t * (drift[:3] + jnp.cross(drift[3:], v))

    if device.marker_reading == "point":
        return on_position(y)
    if device.marker_reading == "frame":
        Rn = exp_so3(t * drift[3:]) @ y[:3, :3]
        top = jnp.concatenate([Rn, on_position(y[:3, 3])[:, None]], axis=1)
        return jnp.concatenate([top, y[3:]], axis=0)
    raise ValueError(f"gap diagnosis supports position and pose devices, not {device.kind!r}")


def residuals(model: GapModel, x, q, y, cov, w):
    """Weighted residuals (N, m): w * (measured - predicted), all samples."""
    pred = jax.vmap(functools.partial(read, model, x))(q, cov)
    return jax.vmap(model.device.residual)(pred, y) * w


__all__ = ["EFFECTS", "GLOBAL_EFFECTS", "JOINT_EFFECTS", "NEEDS", "GapModel", "gap_model", "read", "residuals", "tool_pose"]
