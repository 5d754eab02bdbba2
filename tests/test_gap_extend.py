"""Adding an effect to the gap library in one place: an `Effect` subclass defined here, registered, found by
`jc.gap.diagnose` on data generated with it (no other file edited)."""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.gap.effect import Effect, register, registered_effects, unregister
from jaxcal.gap.effects import EFFECTS

NOISE = 2e-5


class JointOffsetByTemperature(Effect):
    """A revolute joint's zero drifting with temperature: dq_j = k_j * tau (tau the standardised temperature)."""

    name = "joint_offset_by_temperature"
    per_joint = True
    acts_on = frozenset({"joint"})
    needs = "thermal"

    def applies(self, joint, revolute):
        return revolute

    def input_basis(self, q, c):
        return jnp.full((q.shape[0], 1), c.thermal)


@pytest.fixture
def temperature_offset():
    effect = register(JointOffsetByTemperature())
    yield effect
    unregister(effect.name)


def test_a_registered_effect_is_laid_out_and_diagnosed(temperature_offset):
    robot = jc.robots.get("mrr1")
    model = jc.gap.gap_model(robot, jc.make_device("position"))
    revolute = [n for n, r in zip(robot.joint_names, model.revolute) if r]
    assert registered_effects()[-1] == temperature_offset.name and temperature_offset.name not in EFFECTS
    assert [n for n in model.effect_names if "temperature" in n] == [f"gap.{temperature_offset.name}.{j}" for j in revolute]

    n = 60
    rng = np.random.default_rng(0)
    q = jc.random_configurations(robot, n, seed=1)
    cov = {"temperature": 20 + 2 * np.sin(np.linspace(0, 3, n)) + rng.normal(0, 0.02, n)}
    truth = {f"gap.{temperature_offset.name}.j2": 3e-4}  # rad per standard deviation of temperature
    data = jc.gap.simulate_effect(robot, jc.perturb(robot, 1e-3, seed=2), q, "position", truth, cov, noise=NOISE)
    d = jc.gap.diagnose(robot, data)
    best = d.ranking[0]
    assert (best.effect, best.joints) == (temperature_offset.name, ("j2",)), d.report()
    assert d.verdict == temperature_offset.name and d.joints == ("j2",), d.report()
    assert abs(d.parameters[f"gap.{temperature_offset.name}.j2"] / 3e-4 - 1) < 0.15, d.parameters


def test_unregistering_restores_the_built_in_layout(temperature_offset):
    robot = jc.robots.get("mrr1")
    with_it = jc.gap.gap_model(robot, jc.make_device("position"))
    unregister(temperature_offset.name)
    try:
        without = jc.gap.gap_model(robot, jc.make_device("position"))
        assert registered_effects() == EFFECTS
        assert without.effect_names == tuple(n for n in with_it.effect_names if temperature_offset.name not in n)
    finally:
        register(temperature_offset)


@pytest.mark.parametrize("robot_name", ["kr6", "stanford", "mrr1"])
def test_joint_axes_turn_the_tip_as_the_kinematics_do(robot_name):
    """For every revolute joint j, d(tip)/dq_j = z_j x (tip - o_j) with (o_j, z_j) from `joint_axes`: checked
    against jax.jacfwd of the forward kinematics for a standard-DH table (KR6: the axis is the parent's z),
    modified DH (Stanford) and PRY modules (MRR-1: the axis passes through the parent's origin)."""
    import jax

    from jaxcal.gap.effects import gap_model, joint_axes
    from jaxcal.kin.model import frames_single, joint_variables

    if robot_name == "kr6":
        rb = jc.load_robot(os.path.join(os.path.dirname(jc.__file__), "robots", "data", "kr6_r900_dh.yaml"))
    else:
        rb = jc.robots.get(robot_name)
    model = gap_model(rb, jc.make_device("position"))
    a = jnp.asarray(jc.perturb(rb, {"length": 0.01, "angle": 0.01}, seed=3))  # gains stay 1: d(tip)/dq_j is then the axis term
    q = jnp.asarray(jc.random_configurations(rb, 1, seed=4)[0])
    F = frames_single(rb, a, joint_variables(rb, a, q))
    o, z = joint_axes(model, F)
    tip = F.p[rb.tip]
    J = jax.jacfwd(lambda v: jc.forward(rb, a, v).p)(q)
    for j, revolute in enumerate(model.revolute):
        want = np.asarray(J[:, j])
        got = np.cross(np.asarray(z[j]), np.asarray(tip - o[j])) if revolute else np.asarray(z[j])
        np.testing.assert_allclose(got, want, atol=1e-12, err_msg=f"{robot_name} joint {j}")
