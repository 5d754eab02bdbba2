"""The effect interface of the gap diagnosis: one `Effect` object per unmodelled effect, and the registry.

An effect is a small differentiable extension of the forward model. Its parameters theta form one block
per joint (`per_joint`: shape (n_joints, len(terms)), zero rows where it does not apply) or one global
vector (len(terms),), all of typical size `scale`. It acts at the places named in `acts_on`, and the
evaluators (`jaxcal.gap.effects` for open chains, `jaxcal.gap.closed` for closed loops) call the matching
hook with theta and the sample's covariates c = (time, thermal driver, direction per joint):

  "joint"          joint input offsets, linear in theta: dq_j = sum_t theta_jt phi_jt(q, c)
                   (`input_basis` gives phi; open chains and closed loops)
  "gravity"        rotation vectors dphi_j (n, 3) about each joint axis from the gravity moments M_j (open chains)
  "payload"        the same hook (`tool_rotation`) with the moments P_j = (p - o_j) x g_hat of a unit mass at the
                   tool point p instead (open chains)
  "actuator_load"  actuator input offsets dq_j from the gravity load tau_j on each actuator (closed loops)
  "tool"           a transform of the tool pose (R, p) in the robot base frame
  "reading"        an additive change dv of a position reading v, and optionally a rotation vector turning
                   a frame reading (device frame)

Adding an effect: subclass `Effect`, implement the hooks of `acts_on`, `register` an instance. Its
parameters are named "gap.<effect>[.<joint>][.<term>]" and `diagnose` ranks it with the built-in ones.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, NamedTuple

import jax.numpy as jnp

EFFECT_SCALE = 1e-3  # typical size of an effect parameter (rad, m, or relative)
PLACES = frozenset({"joint", "gravity", "payload", "actuator_load", "tool", "reading"})
COVARIATES = ("direction", "thermal", "time")


class Covariates(NamedTuple):
    """Covariates of one sample, as the hooks see them."""

    time: Any  # standardised time (scalar)
    thermal: Any  # standardised temperature, else standardised time (scalar)
    direction: Any  # direction of approach per joint (n,), +-1 (0 when unknown)


def covariates_of(cov) -> Covariates:
    """View of one row (2 + n_joints,) of the covariate matrix (`jaxcal.gap.fit.covariate_matrix`)."""
    return Covariates(cov[0], cov[1], cov[2:])


class Effect(abc.ABC):
    """One effect of the library. Subclasses set the class attributes and the hooks of `acts_on`."""

    name: ClassVar[str]
    per_joint: ClassVar[bool]
    acts_on: ClassVar[frozenset[str]]
    terms: ClassVar[tuple[str, ...]] = ("",)  # parameter terms per joint (or of the global block); "" = unnamed
    needs: ClassVar[str | None] = None  # covariate without which the effect is not a candidate
    closed_loop: ClassVar[bool] = True  # in the closed-loop library (its hooks make sense through a closure)
    scale: ClassVar[float] = EFFECT_SCALE

    def applies(self, joint: int, revolute: bool) -> bool:
        """Whether a per-joint effect has parameters at joint input `joint`."""
        return True

    def parameter_names(self, joint_name: str | None = None) -> list[str]:
        """"gap.<effect>[.<joint>][.<term>]" for each term."""
        stem = f"gap.{self.name}" + (f".{joint_name}" if joint_name else "")
        return [stem + (f".{t}" if t else "") for t in self.terms]

    def input_basis(self, q, c: Covariates):
        """phi (n, k) with dq_j = sum_t theta_jt phi_jt ("joint")."""
        raise NotImplementedError(self.name)

    def joint_offset(self, theta, q, c: Covariates):
        """dq (n,) added to the joint inputs q ("joint")."""
        return jnp.sum(theta * self.input_basis(q, c), axis=1)

    def tool_rotation(self, theta, loads, axes):
        """dphi (n, 3), rad: rotation about joint axis j of everything distal, from the gravity moments
        loads = M (n, 3; kg m) and the unit axes z (n, 3) ("gravity"; "payload": the moments of 1 kg at the tool)."""
        raise NotImplementedError(self.name)

    def actuator_offset(self, theta, load):
        """dq (n,) added to the actuator inputs from the gravity load tau (n,; kg m) on each actuator ("actuator_load")."""
        raise NotImplementedError(self.name)

    def tool_transform(self, theta, R, p, origin, c: Covariates):
        """(R', p'): the tool pose changed by the effect; origin: the robot base origin ("tool")."""
        raise NotImplementedError(self.name)

    def reading_offset(self, theta, v, c: Covariates):
        """dv (3,): change of the position reading v (device frame) ("reading")."""
        raise NotImplementedError(self.name)

    def reading_rotation(self, theta, c: Covariates):
        """Rotation vector turning a frame reading, or None when the effect turns none ("reading")."""
        return None

    def box_limit(self, box: float, peak_load: float) -> float:
        """Largest sane change of one parameter in a refit: `box` (m, rad or relative) for effects that
        offset a joint, the tool or the reading directly; overridden by the gravity effects."""
        return box


def load_box(box: float, peak_load: float) -> float:
    """Box of an effect proportional to a gravity load: box / max_samples |M_j| (kg m), so that its deflection
    theta |M_j| stays within `box` rad; unbounded at a joint that carries no load."""
    return box / peak_load if peak_load > 0 else float("inf")


_REGISTRY: dict[str, Effect] = {}


def register(effect: Effect) -> Effect:
    """Add an effect to the library (the end of the order `registered_effects` gives); returns it."""
    if effect.name in _REGISTRY:
        raise ValueError(f"effect {effect.name!r} is already registered")
    if not effect.acts_on or not effect.acts_on <= PLACES:
        raise ValueError(f"effect {effect.name!r}: acts_on must be a non-empty subset of {sorted(PLACES)}")
    if effect.needs is not None and effect.needs not in COVARIATES:
        raise ValueError(f"effect {effect.name!r}: needs must be one of {COVARIATES} or None")
    _REGISTRY[effect.name] = effect
    return effect


def unregister(name: str) -> None:
    """Remove an effect from the library (models built before keep it)."""
    _REGISTRY.pop(name)


def get_effect(name: str) -> Effect:
    if name not in _REGISTRY:
        raise KeyError(f"unknown effect {name!r}; registered: {registered_effects()}")
    return _REGISTRY[name]


def registered_effects() -> tuple[str, ...]:
    """Names of the registered effects, in registration order (the order of the ranking's ties)."""
    return tuple(_REGISTRY)


__all__ = ["COVARIATES", "EFFECT_SCALE", "PLACES", "Covariates", "Effect", "covariates_of", "get_effect", "load_box", "register",
           "registered_effects", "unregister"]
