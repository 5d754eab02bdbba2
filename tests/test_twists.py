"""The open chains' residual Jacobian from parameter twists (`jaxcal.kin.twists`, `core.open_residual_and_jacobian`)
against the reverse-mode Jacobian of the plain residual (`core.data_residual_and_jacobian`, which differentiates
`forward` and the device's reading with no twist algebra) and against central differences: every open convention
(modified DH with gains and coupled joints, standard DH with a joint driven by two others, PRY with a base frame and
with every module kind, URDF, a planar chain that reads its parent, MCPC), every device kind, a tree read at two tips,
and the frames-only (robot held) case."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import central_fd, rel_err
from helpers import device, device_frame, mcpc_spatial

import jaxcal as jc
from jaxcal.fit import core
from jaxcal.fit.identify import residual_weights
from jaxcal.kin.convention import Convention, get_convention
from jaxcal.kin.model import Body, Robot, forward_open
from jaxcal.kin.twists import tools_and_twists
from jaxcal.measure.registry import registered_kinds
from jaxcal.robots.build import pry_robot
from jaxcal.robots.io import robot_from_dict

SINGLE_TOOL_KINDS = tuple(k for k in registered_kinds() if k != "link_camera")


def _coupled_stanford():
    """The Stanford arm with gains and both coupling matrices of seed 001 eq 4 (made up, full rank)."""
    import os

    with open(os.path.join(os.path.dirname(jc.__file__), "robots", "data", "stanford.yaml")) as f:
        doc = yaml.safe_load(f)
    for j in range(1, 7):
        doc["frames"][j][6] = 1.0 + 0.05 * j
    Cm = np.eye(6)
    Cm[4, 3] = 0.5
    Cj = np.eye(6)
    Cj[5, 4] = -0.2
    doc["coupling"] = {"Cm": Cm.tolist(), "Cj": Cj.tolist()}
    return robot_from_dict(doc, "stanford_coupled.yaml")


def _coupled_torso():
    """Standard DH (its twists by forward mode) with a joint driven by two others: 5 inputs, 6 joint variables."""
    return robot_from_dict({
        "name": "torso_arm", "convention": "standard_dh", "columns": ["name", "parent", "type", "theta", "d", "a", "alpha"],
        "joints": [["t1", "base", "R", 0.0, 0.4, 0.1, 0.0], ["t2", "t1", "R", 0.2, 0.0, 0.3, 0.0],
                   ["t3", "t2", "R", 0.0, 0.0, 0.05, 1.57], ["s1", "t3", "R", 0.1, 0.2, 0.0, -1.57],
                   ["s2", "s1", "R", -0.3, 0.0, 0.35, 0.0], ["e1", "s2", "R", 0.0, 0.05, 0.3, 1.2]],
        "coupling": {"t3": {"t1": -1, "t2": -1, "offset": 0.1}}}, "torso.yaml")


def _planar_chain():
    """An open three-link planar chain (absolute joint angles: each body reads its parent's row and angle)."""
    bodies = tuple(Body(f"l{i}", "planar", 0, i - 1, (2 * i, 2 * i + 1), (i,)) for i in range(3))
    names = tuple(f"l{i}.{n}" for i in range(3) for n in ("a", "phi"))
    return Robot("planar3", bodies, names, np.array([0.5, 0.1, 0.4, -0.2, 0.3, 0.05]), ("length", "angle") * 3,
                 np.ones(6, bool), np.ones(6), ("q0", "q1", "q2"), np.zeros(3), -np.pi * np.ones(3), np.pi * np.ones(3))


def _pry_kinds():
    """A PRY chain with every multi-input module kind (their twists by forward mode)."""
    return pry_robot("allkinds", (0, 0, 0.1), [("cylindrical", (0.1, 0, 0), (0, 0, 0)), ("universal", (0.2, 0, 0), (0.1, 0, 0)),
                                               ("spherical", (0, 0, 0.1), (0, 0.2, 0)), ("revolute", (0.1, 0.05, 0), (0.1, 0, 0.2))])


def _two_hands():
    import os

    from jaxcal.robots.real_datasets import DATA_DIR

    return jc.load_robot(os.path.join(DATA_DIR, "talos", "talos.urdf"), base="base_link",
                         tips=["arm_left_7_link", "arm_right_7_link"])


ROBOTS = {"stanford": lambda: jc.robots.get("stanford"), "coupled": _coupled_stanford, "mrr1": lambda: jc.robots.get("mrr1"),
          "talos": lambda: jc.robots.get("talos_left_arm"), "planar": _planar_chain, "mcpc": mcpc_spatial,
          "pry_kinds": _pry_kinds, "torso": _coupled_torso, "two_hands": _two_hands}


@functools.cache
def _robot(name):
    return ROBOTS[name]()


def _case(robot_name, kind, n=4, seed=0):
    """(model, x, q, y, w): readings of a perturbed robot in a rotated device frame metres away, 1 mm / 1 mrad off
    the model, at a point x away from both the truth and the nominal (every residual nonzero, every twist used)."""
    rb = _robot(robot_name)
    dev = device(kind)
    q = jnp.asarray(jc.random_configurations(rb, n, seed=seed))
    a_true = jc.perturb(rb, {"length": 2e-3, "angle": 3e-3, "gain": 2e-3}, seed=seed + 1)
    d = np.asarray(device_frame(kind))
    data = jc.simulate(rb, a_true, q, dev, device_params=d, noise=1e-3, seed=seed + 2)
    x = jnp.concatenate([jc.perturb(rb, 1e-3, seed=seed + 3), jnp.asarray(d) + 1e-3])
    w = np.broadcast_to(residual_weights(dev), (n, len(residual_weights(dev))))
    return core.RobotDevice(rb, dev), x, q, jnp.asarray(data.y), jnp.asarray(w)


def _reference(model, x, q, y, w):
    """Reverse mode through `forward` and the reading, sample by sample (no twists)."""
    return jax.jit(core.data_residual_and_jacobian, static_argnums=0)(model, x, q, y, jnp.zeros((len(q), 0)), w)


def _twists(model, x, q, y, w, held=False):
    return jax.jit(core.open_residual_and_jacobian, static_argnums=(0, 1))(model.robot, model.device, x, q, y, w, held)


@pytest.mark.parametrize("robot_name", ["stanford", "coupled", "mrr1", "talos", "planar", "mcpc", "pry_kinds",
                                        "torso"])
def test_open_chains_match_reverse_mode(robot_name):
    """Every open convention read as full poses (the device test below covers every reading on one robot): r equal,
    J to 1e-12 relative (measured 1e-16..1e-15), the same columns nonzero."""
    model, x, q, y, w = _case(robot_name, "pose")
    r0, J0 = _reference(model, x, q, y, w)
    r1, J1 = _twists(model, x, q, y, w)
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-12)
    assert rel_err(J1, J0) < 1e-12, (robot_name, rel_err(J1, J0))
    moves = lambda J: np.any(np.asarray(J)[:, :model.robot.n_params] != 0, axis=0)  # noqa: E731
    np.testing.assert_array_equal(moves(J1), moves(J0))


@pytest.mark.parametrize("kind", SINGLE_TOOL_KINDS)
def test_every_device_matches_reverse_mode(kind):
    """The wrench of every device's reading (its derivative along the tool's unit twists) is right: Stanford arm."""
    model, x, q, y, w = _case("stanford", kind)
    r0, J0 = _reference(model, x, q, y, w)
    r1, J1 = _twists(model, x, q, y, w)
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-12)
    assert rel_err(J1, J0) < 1e-12, (kind, rel_err(J1, J0))


def test_a_tree_read_at_two_tips():
    """TALOS read at both hands by a camera on one and a marker on the other: each hand moves with the parameters
    on its own path only."""
    model, x, q, y, w = _case("two_hands", "link_camera", n=3)
    r0, J0 = _reference(model, x, q, y, w)
    r1, J1 = _twists(model, x, q, y, w)
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-12)
    assert rel_err(J1, J0) < 1e-12, rel_err(J1, J0)


def test_central_differences_and_held_robot():
    """Stanford arm with coupled gains, poses: J against central differences of the residual (h = 1e-6, relative
    error < 1e-7; measured ~1e-10); robot held: the robot's columns are exactly 0, the device's unchanged."""
    model, x, q, y, w = _case("coupled", "pose", n=3)
    _, J = _twists(model, x, q, y, w)

    def f(v):
        return core.residuals(model.robot, model.device, jnp.asarray(v), q, y, w).reshape(-1)

    assert rel_err(J, central_fd(f, np.asarray(x))) < 1e-7
    _, J_held = _twists(model, x, q, y, w, True)
    nr = model.robot.n_params
    assert np.all(np.asarray(J_held)[:, :nr] == 0)
    np.testing.assert_array_equal(np.asarray(J_held)[:, nr:], np.asarray(J)[:, nr:])


def test_tools_are_the_forward_kinematics():
    for name in ("stanford", "coupled", "mrr1", "planar", "two_hands", "torso"):
        rb = _robot(name)
        qi = jnp.asarray(jc.random_configurations(rb, 1, seed=5)[0])
        tools, Xi = tools_and_twists(rb, rb.nominal, qi)
        ref = forward_open(rb, rb.nominal, qi)
        np.testing.assert_allclose(tools.R, ref.R, atol=1e-15)
        np.testing.assert_allclose(tools.p, ref.p, atol=1e-15)
        assert Xi.shape == (rb.n_tips, rb.n_params, 6)


AXIS = tuple(np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81]))


@pytest.mark.parametrize("convention, kind", [("mdh", 0), ("mdh", 1), ("mdh", 2), ("urdf", ("revolute", AXIS)),
                                              ("urdf", ("prismatic", AXIS)), ("urdf", ("fixed", AXIS)),
                                              ("pry", "revolute"), ("pry", "prismatic"), ("pry", "cylindrical"),
                                              ("pry", "fixed")])
def test_closed_form_twists(convention, kind):
    """The conventions' closed-form input twists equal the generic ones by forward mode (`Convention.local_twists`)."""
    conv = get_convention(convention)
    rng = np.random.default_rng(0)

    @jax.jit  # compiled whole, not op by op
    def closed_and_generic(row, qv):
        frame = conv.local_transform(row, kind, qv)
        return conv.local_twists(row, kind, qv, frame), Convention.local_twists(conv, row, kind, qv, frame)

    for _ in range(5):
        row = jnp.asarray(rng.uniform(-1.5, 1.5, len(conv.row_names)))
        qv = jnp.asarray(rng.uniform(-2, 2, conv.n_inputs(kind)))
        closed, generic = closed_and_generic(row, qv)
        assert closed.shape == (len(conv.row_names) + conv.n_inputs(kind), 6)
        np.testing.assert_allclose(closed, generic, rtol=0, atol=1e-14)


def test_chunks_with_a_remainder(monkeypatch):
    """Samples split into chunks of 3 with a remainder (`core.JACOBIAN_CHUNK`, read when traced) give the same r, J."""
    model, x, q, y, w = _case("stanford", "pose", n=4)
    r0, J0 = _reference(model, x, q, y, w)
    monkeypatch.setattr(core, "JACOBIAN_CHUNK", 3)
    r1, J1 = jax.jit(lambda v: core.open_residual_and_jacobian(model.robot, model.device, v, q, y, w))(x)
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-12)
    assert rel_err(J1, J0) < 1e-12
