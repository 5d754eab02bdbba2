"""The effect model of a (robot, device): parameter layout and the evaluation steps open chains and closed
loops share.

One `GapModel` holds every registered effect's parameters in one vector appended to the robot and device
parameters, x = [a_robot, d_device, e_effects]. A candidate switches effects on by a mask (the others stay
pinned at zero), so one compiled solver serves every candidate, every joint-restricted variant and every
fold. Layout of e: for each joint input j, the per-joint effects that apply there (registry order, each with
its terms), then the global effects (registry order). Closed-loop robots get the effects with `closed_loop`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

import jaxcal.gap.library  # noqa: F401  (registers the built-in effects)
from jaxcal.gap.effect import Effect, covariates_of, get_effect, registered_effects
from jaxcal.kin.model import Robot
from jaxcal.kin.rotations import exp_so3
from jaxcal.measure.devices import Device

G_HAT = np.array([0.0, 0.0, -1.0])  # gravity direction in the robot base frame (load in kg m)


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
    effects: tuple[Effect, ...] = ()  # the effects of the layout, registry order

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

    def effect(self, name: str) -> Effect:
        return next(fx for fx in self.effects if fx.name == name)

    def acting_on(self, place: str) -> tuple[Effect, ...]:
        """The model's effects acting at `place` (see `jaxcal.gap.effect`)."""
        return tuple(fx for fx in self.effects if place in fx.acts_on)

    def nominal(self) -> np.ndarray:
        return np.concatenate([self.robot.nominal_np, self.device.nominal_np, np.zeros(len(self.effect_names))])

    def x_scale(self) -> np.ndarray:
        units = tuple(self.robot.units) + tuple(self.device.units)
        geo = [1.0 if u in ("gain", "scale") else 0.01 for u in units]
        return np.array(geo + [self.effect(e).scale for e in self.effect_of])


def _descendants(robot: Robot, b: int) -> tuple[int, ...]:
    out = []
    for k in range(len(robot.bodies)):
        i = k
        while i >= 0:
            if i == b:
                out.append(k)
                break
            i = robot.bodies[i].parent
    return tuple(out)


def _urdf_masses(robot: Robot):
    """(mass per body, centre of mass per body) from the URDF inertials, or ((), ()) when the robot has none."""
    inertia = robot.extras.get("inertia") if robot.extras else None
    if not inertia or len(inertia) != len(robot.bodies) or sum(b["mass"] for b in inertia) <= 0:
        return (), ()
    return (tuple(float(b["mass"]) for b in inertia),
            tuple(tuple(float(c) for c in np.asarray(b["com"], float)) for b in inertia))


def _layout(robot: Robot, revolute, effects):
    """(names, effect_of, joint_of) of the effect parameters: per joint, then global (see the module docstring)."""
    rows = []
    for j, joint in enumerate(robot.joint_names):
        for fx in effects:
            if fx.per_joint and fx.applies(j, revolute[j]):
                rows += [(name, fx.name, j) for name in fx.parameter_names(joint)]
    for fx in effects:
        if not fx.per_joint:
            rows += [(name, fx.name, -1) for name in fx.parameter_names()]
    return tuple(zip(*rows)) if rows else ((), (), ())


@functools.lru_cache(maxsize=64)
def _cached_model(robot: Robot, device: Device, effects: tuple[Effect, ...]) -> GapModel:
    joint_body = []
    for j in range(robot.n_inputs):
        owners = [b for b, body in enumerate(robot.bodies) if j in body.inputs]
        if not owners:
            raise ValueError(f"robot {robot.name!r}: joint input {j} is consumed by no body")
        joint_body.append(owners[0])
    revolute = tuple(robot.bodies[b].conv.is_revolute(robot.bodies[b].kind) for b in joint_body)
    names, eff, jnt = _layout(robot, revolute, effects)
    distal = tuple(_descendants(robot, b) for b in joint_body)
    mass, com = _urdf_masses(robot)
    return GapModel(robot, device, names, eff, jnt, tuple(joint_body), revolute, distal, mass, com,
                    tuple(fx for fx in effects if fx.name in eff))


def gap_model(robot: Robot, device: Device) -> GapModel:
    """The effect model of a robot and device with the registered effects (cached, so compiled solvers are
    shared); a closed-loop robot gets those with `closed_loop` (the effects act through its closure)."""
    effects = tuple(get_effect(name) for name in registered_effects())
    if robot.closure is not None:
        effects = tuple(fx for fx in effects if fx.closed_loop)
    return _cached_model(robot, device, effects)


def block_index(model: GapModel, effect: str) -> np.ndarray:
    """Static (n_joints, k) index of a per-joint effect's parameters in e; -1 where it does not apply."""
    idx = -np.ones((model.robot.n_inputs, len(model.effect(effect).terms)), int)
    seen: dict = {}
    for i, (ef, j) in enumerate(zip(model.effect_of, model.joint_of)):
        if ef == effect:
            idx[j, seen.get(j, 0)] = i
            seen[j] = seen.get(j, 0) + 1
    return idx


def params_of(model: GapModel, e, fx: Effect):
    """theta of one effect from the effect vector e: the dense (n_joints, k) block of a per-joint effect
    (zeros where it does not apply), the (k,) vector of a global one."""
    if fx.per_joint:
        return jnp.append(e, 0.0)[jnp.asarray(block_index(model, fx.name))]
    return e[jnp.asarray([i for i, ef in enumerate(model.effect_of) if ef == fx.name])]


def joint_offsets(model: GapModel, e, q, cov):
    """dq (n,) added to the joint inputs q: the sum of the "joint" effects."""
    c = covariates_of(cov)
    dq = jnp.zeros_like(q)
    for fx in model.acting_on("joint"):
        dq = dq + fx.joint_offset(params_of(model, e, fx), q, c)
    return dq


def tool_transforms(model: GapModel, e, R, p, cov):
    """The tool pose (R, p) through the "tool" effects in turn (about the robot base origin)."""
    robot = model.robot
    origin = robot.base.p if robot.base is not None else jnp.zeros(3)
    c = covariates_of(cov)
    for fx in model.acting_on("tool"):
        R, p = fx.tool_transform(params_of(model, e, fx), R, p, origin, c)
    return R, p


def reading_effects(model: GapModel, e, y, cov):
    """A device reading through the "reading" effects: position v + sum of dv (each from the unchanged v);
    a frame reading's rotation turned by exp(sum of the rotation vectors)."""
    c = covariates_of(cov)
    fxs = model.acting_on("reading")
    thetas = [params_of(model, e, fx) for fx in fxs]

    def on_position(v):
        out = v
        for fx, theta in zip(fxs, thetas):
            out = out + fx.reading_offset(theta, v, c)
        return out

    if model.device.marker_reading == "point":
        return on_position(y)
    if model.device.marker_reading == "points":
        return jax.vmap(on_position)(y)
    if model.device.marker_reading == "frame":
        turns = [r for r in (fx.reading_rotation(theta, c) for fx, theta in zip(fxs, thetas)) if r is not None]
        R = exp_so3(sum(turns)) @ y[:3, :3] if turns else y[:3, :3]
        top = jnp.concatenate([R, on_position(y[:3, 3])[:, None]], axis=1)
        return jnp.concatenate([top, y[3:]], axis=0)
    raise ValueError(f"gap diagnosis supports position, multi-marker and pose devices, not {model.device.kind!r}")


def input_basis(model: GapModel, q, cov) -> np.ndarray:
    """Phi (N, n_effect_params): phi of each "joint" effect parameter at each sample (dq_j = sum theta phi),
    zero for the other parameters. At zero effects d r / d theta_p = phi_p d r / d q_j(p)."""
    out = np.zeros((len(q), len(model.effect_names)))
    for fx in model.acting_on("joint"):
        idx = block_index(model, fx.name)
        phi = np.asarray(jax.vmap(lambda qi, ci, fx=fx: fx.input_basis(qi, covariates_of(ci)))(jnp.asarray(q),
                                                                                            jnp.asarray(cov)))
        used = idx >= 0
        out[:, idx[used]] = phi[:, used]
    return out


__all__ = ["G_HAT", "GapModel", "block_index", "gap_model", "input_basis", "joint_offsets", "params_of", "reading_effects",
           "tool_transforms"]
