"""URDF import and export: forward kinematics against an independent homogeneous-matrix chain,
gradients against finite differences, bad input, and the export/re-import round trip."""

import os
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.robots.urdf import URDFError, load_urdf, matrix_rpy, robot_from_urdf, rpy_matrix, save_urdf

REAL = os.path.join(os.path.dirname(jc.__file__), "robots", "data", "real")
REAL_CHAINS = [("talos/talos.urdf", "gripper_left_base_link"), ("ur10/ur10.urdf", "wrist_3_link"),
               ("tiago/tiago.urdf", "wrist_ft_tool_link")]

# Every supported joint type, tilted axes, non-trivial rpy, fixed joints before, between and after
# the moving ones, and a side branch that is not part of the chain.
ARM = """<?xml version="1.0"?>
<robot name="arm">
  <link name="world"/>
  <link name="base"><inertial><origin xyz="0 0 0.05"/><mass value="3.0"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
  <link name="l1"><inertial><origin xyz="0.1 0 0" rpy="0 0 0.3"/><mass value="2.0"/>
    <inertia ixx="0.02" ixy="0.001" ixz="0" iyy="0.03" iyz="0" izz="0.04"/></inertial></link>
  <link name="l1b"><inertial><origin xyz="0 0.2 0"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="l2"/>
  <link name="l3"/>
  <link name="tool"/>
  <link name="camera"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.1 -0.2 0.3"/></joint>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.4" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="bracket" type="fixed"><parent link="l1"/><child link="l1b"/>
    <origin xyz="0.05 0.01 0" rpy="1.5707963267948966 0 0"/></joint>
  <joint name="j2" type="continuous"><parent link="l1b"/><child link="l2"/>
    <origin xyz="0.3 0 0.02" rpy="0.2 0.4 -0.7"/><axis xyz="1 1 0"/></joint>
  <joint name="j3" type="prismatic"><parent link="l2"/><child link="l3"/>
    <origin xyz="0 0.1 0.25" rpy="-0.3 0 1.1"/><axis xyz="0 0 -1"/><limit lower="0" upper="0.3" effort="1" velocity="1"/></joint>
  <joint name="flange" type="fixed"><parent link="l3"/><child link="tool"/>
    <origin xyz="0.01 0.02 0.12" rpy="3.0 0.1 -2.9"/></joint>
  <joint name="cam" type="fixed"><parent link="l1"/><child link="camera"/><origin xyz="0 0 1"/></joint>
  <gazebo reference="l1"><material>Gazebo/Grey</material></gazebo>
</robot>
"""


def independent_fk(text, base, tip, q):
    """Tip frame by plain 4x4 products over the XML (ElementTree): T = prod origin_i * motion_i."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    chain, link = [], tip
    while link != base:
        j = by_child[link]
        chain.append(j)
        link = j.find("parent").get("link")
    T, k = np.eye(4), 0
    for j in reversed(chain):
        o = j.find("origin")
        xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
        r, p, y = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
        R = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                      [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                      [-sp, cp * sr, cp * cr]])
        O = np.eye(4)
        O[:3, :3], O[:3, 3] = R, xyz
        M = np.eye(4)
        if j.get("type") != "fixed":
            ax = j.find("axis")
            u = np.array([float(v) for v in (ax.get("xyz") if ax is not None else "1 0 0").split()])
            u = u / np.linalg.norm(u)
            if j.get("type") == "prismatic":
                M[:3, 3] = u * q[k]
            else:
                K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
                M[:3, :3] = np.eye(3) + np.sin(q[k]) * K + (1 - np.cos(q[k])) * K @ K
            k += 1
        T = T @ O @ M
    return T


def pose_matrix(rb, a, q):
    return np.asarray(jc.forward(rb, a, q).matrix())


def test_rpy_conventions_roundtrip(rng):
    for _ in range(50):
        rpy = rng.uniform([-np.pi, -np.pi / 2, -np.pi], [np.pi, np.pi / 2, np.pi])
        assert np.allclose(rpy_matrix(matrix_rpy(rpy_matrix(rpy))), rpy_matrix(rpy), atol=1e-13)
    gimbal = rpy_matrix([0.4, np.pi / 2, -0.3])
    assert np.allclose(rpy_matrix(matrix_rpy(gimbal)), gimbal, atol=1e-12)
    # fixed-axis X-Y-Z: roll acts first, about the fixed x axis
    assert np.allclose(rpy_matrix([0.3, 0.0, 0.0]) @ [0, 1, 0], [0, np.cos(0.3), np.sin(0.3)])


def test_synthetic_arm_structure_and_fk(rng):
    rb = robot_from_urdf(ARM, base="world", tip="tool", source="arm.urdf")
    assert rb.joint_names == ("j1", "j2", "j3")
    assert [b.name for b in rb.bodies] == ["j1", "j2", "j3", "flange"]
    assert rb.n_params == 3 * 7 + 6
    assert "j2.offset" in rb.names and "flange.yaw" in rb.names and "flange.offset" not in rb.names
    assert rb.extras["urdf_bodies"][0]["folded"] == ("mount",) and rb.extras["urdf_bodies"][1]["folded"] == ("bracket",)
    assert np.allclose(rb.q_min, [-2, -np.pi, 0]) and np.allclose(rb.q_max, [2, np.pi, 0.3])
    assert rb.units[rb.index("j3.offset")] == "length" and rb.units[rb.index("j1.offset")] == "angle"
    Q = rng.uniform(rb.q_min, rb.q_max, (20, 3))
    got = pose_matrix(rb, rb.nominal, Q)
    for k, q in enumerate(Q):
        assert np.max(np.abs(got[k] - independent_fk(ARM, "world", "tool", q))) < 1e-12


def test_inertia_of_folded_links():
    rb = robot_from_urdf(ARM, base="world", tip="tool")
    body1 = rb.extras["inertia"][0]
    assert body1["links"] == ("l1", "l1b")
    assert body1["mass"] == pytest.approx(3.0)
    # l1b's com (0, 0.2, 0) in l1b; l1b = Trans(0.05, 0.01, 0) Rx(pi/2) in l1 -> (0.05, 0.01, 0.2) in l1
    assert np.allclose(body1["com"], (2.0 * np.array([0.1, 0, 0]) + 1.0 * np.array([0.05, 0.01, 0.2])) / 3.0)
    I = body1["inertia"]
    assert np.allclose(I, I.T) and np.all(np.linalg.eigvalsh(I) > 0)
    assert rb.extras["inertia"][3]["mass"] == 0.0  # the closing fixed body moves with j3's links


@pytest.mark.parametrize("path,tip", REAL_CHAINS)
def test_real_urdf_fk_matches_independent_chain(path, tip, rng):
    full = os.path.join(REAL, path)
    rb = jc.load_robot(full, tip=tip)
    text = open(full).read()
    Q = rng.uniform(rb.q_min, rb.q_max, (10, rb.n_inputs))
    got = pose_matrix(rb, rb.nominal, Q)
    base = rb.extras["base_link"]
    for k, q in enumerate(Q):
        assert np.max(np.abs(got[k] - independent_fk(text, base, tip, q))) < 1e-12


def test_jacobian_matches_finite_differences(rng):
    rb = robot_from_urdf(ARM, base="world", tip="tool")
    Q = rng.uniform(rb.q_min, rb.q_max, (4, 3))
    a0 = np.asarray(rb.nominal) + rng.normal(0, 0.01, rb.n_params)
    f = jax.jit(lambda a: jc.forward(rb, a, Q).matrix()[..., :3, :].reshape(-1))
    J = np.asarray(jax.jacfwd(f)(jnp.asarray(a0)))
    J_fd = central_fd(f, a0, h=1e-6)
    assert rel_err(J, J_fd) < 1e-8  # measured ~1e-10 (central differences, h = 1e-6)
    g = jax.jit(lambda q: jc.forward(rb, a0, q).p)
    q0 = rng.uniform(rb.q_min, rb.q_max)
    assert rel_err(np.asarray(jax.jacfwd(g)(jnp.asarray(q0))), central_fd(g, q0)) < 1e-8


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("text,kwargs,expected", [
    (ARM, {"tip": "gripper"}, "no <link name='gripper'>"),
    (ARM, {"base": "l2", "tip": "l1"}, "broken chain: walking up from tip link 'l1' reached <link name='world'>"),
    (ARM.replace("</robot>", ""), {"tip": "tool"}, "malformed XML"),
    (ARM.replace('name="j2" type="continuous"', 'name="j2" type="helical"'), {"tip": "tool"}, "joint[@name='j2']"),
    (ARM.replace('name="j2" type="continuous"', 'name="j2" type="floating"'), {"tip": "tool"}, "<joint name='j2'>: unsupported"),
    (ARM.replace('<child link="camera"/>', '<child link="kamera"/>'), {"tip": "tool"}, "<joint name='cam'>: child link 'kamera'"),
    (ARM.replace('<axis xyz="1 1 0"/>', '<axis xyz="0 0 0"/>'), {"tip": "tool"}, "<joint name='j2'>/<axis>"),
    (ARM.replace('xyz="0.3 0 0.02"', 'xyz="0.3 zero 0.02"'), {"tip": "tool"}, "joint[@name='j2']/origin"),
    (ARM, {}, "give tip="),
])
def test_bad_input_names_file_and_element(tmp_path, text, kwargs, expected):
    path = _write(tmp_path, "bad.urdf", text)
    with pytest.raises(URDFError) as err:
        jc.load_robot(path, **kwargs)
    assert "bad.urdf" in str(err.value) and expected in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(URDFError, match="no such file"):
        load_urdf(str(tmp_path / "none.urdf"))


def test_export_reimport_same_fk(tmp_path, rng):
    src = _write(tmp_path, "arm.urdf", ARM)
    before = open(src).read()
    rb = jc.load_robot(src, base="world", tip="tool")
    a = np.asarray(rb.nominal) + rng.normal(0, 0.02, rb.n_params)  # offsets and geometry all changed
    out = save_urdf(rb, str(tmp_path / "out" / "arm_cal.urdf"), a)
    assert open(src).read() == before
    assert sorted(os.listdir(tmp_path / "out")) == ["arm_cal.urdf"]  # no temp file left
    back = jc.load_robot(out, base="world", tip="tool")
    Q = rng.uniform(rb.q_min, rb.q_max, (25, 3))
    assert np.max(np.abs(pose_matrix(back, back.nominal, Q) - pose_matrix(rb, a, Q))) < 1e-12
    # offsets are folded into the origins: the re-imported zeros are the calibrated ones
    assert all(abs(back.nominal_np[back.index(f"j{i}.offset")]) < 1e-15 for i in (1, 2, 3))
    # the independent reader sees the calibrated robot too, and the rest of the file is kept
    text = open(out).read()
    for q in Q[:5]:
        assert np.max(np.abs(independent_fk(text, "world", "tool", q) - pose_matrix(rb, a, q))) < 1e-12
    assert "<gazebo" in text and 'name="cam"' in text
    assert ET.fromstring(text).find("joint[@name='mount']/origin").get("xyz") == "0.1 -0.2 0.3"


def test_export_real_robot_roundtrip(tmp_path, rng):
    rb = jc.load_robot(os.path.join(REAL, "ur10", "ur10.urdf"), tip="wrist_3_link")
    a = np.asarray(rb.nominal) + rng.normal(0, 0.01, rb.n_params)
    back = jc.load_robot(save_urdf(rb, str(tmp_path / "ur10_cal.urdf"), a), tip="wrist_3_link")
    Q = rng.uniform(rb.q_min, rb.q_max, (10, 6))
    assert np.max(np.abs(pose_matrix(back, back.nominal, Q) - pose_matrix(rb, a, Q))) < 1e-12


def test_export_refuses_input_and_non_urdf_robots(tmp_path):
    src = _write(tmp_path, "arm.urdf", ARM)
    rb = jc.load_robot(src, base="world", tip="tool")
    with pytest.raises(URDFError, match="refusing to overwrite the input"):
        save_urdf(rb, src)
    with pytest.raises(URDFError, match="not loaded from a URDF"):
        save_urdf(jc.robots.get("mrr1"), str(tmp_path / "mrr1.urdf"))
    with pytest.raises(jc.robots.RobotFileError, match="saved as .urdf, not YAML"):
        jc.save_robot(rb, str(tmp_path / "arm.yaml"))
    out = jc.save_robot(rb, str(tmp_path / "copy.urdf"))  # dispatches to save_urdf
    assert jc.load_robot(out, base="world", tip="tool").names == rb.names


@pytest.mark.slow
def test_identify_recovers_urdf_geometry():
    """Base-set identification of the redundant URDF table: simulated position data with a known
    marker frame, perturbed geometry recovered to the noise level."""
    rb = robot_from_urdf(ARM, base="world", tip="tool")
    a_true = jc.perturb(rb, 2e-3, seed=3)
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 60, seed=4), "position", noise=1e-6)
    fit = jc.identify(rb, data)
    assert fit.converged and fit.rms_after < 5e-3 < fit.rms_before


def test_gravity_torques_are_the_potential_gradient(rng):
    """tau_j = d/dq_j sum_i m_i g . c_i(q) (generalised gravity force), by central differences."""
    from jaxcal.kin.model import frames
    from jaxcal.robots.urdf import GRAVITY, gravity_torques

    rb = robot_from_urdf(ARM, base="world", tip="tool")
    mass = np.array([b["mass"] for b in rb.extras["inertia"]])
    com = np.stack([b["com"] for b in rb.extras["inertia"]])

    def work(q):
        f = frames(rb, rb.nominal, q)
        centres = np.asarray(f.p) + np.einsum("bij,bj->bi", np.asarray(f.R), com)
        return np.array([np.sum(mass * (centres @ np.asarray(GRAVITY)))])

    q0 = rng.uniform(rb.q_min, rb.q_max)
    tau = gravity_torques(rb, q0)[0]
    revolute = [0, 1]  # j1, j2 (j3 is prismatic)
    assert np.allclose(tau, central_fd(work, q0)[0, revolute], rtol=1e-7, atol=1e-9)


def test_compliance_model_and_its_jacobian(rng):
    from jaxcal.robots.urdf import compliance_inputs, with_gravity_compliance

    rb = robot_from_urdf(ARM, base="world", tip="tool")
    rc = with_gravity_compliance(rb)
    assert rc.joint_names == ("j1", "j2", "j3", "j1.tau", "j2.tau") and "j2.compliance" in rc.names
    Q = rng.uniform(rb.q_min, rb.q_max, (5, 3))
    X = compliance_inputs(rb, Q)
    a = np.asarray(rc.nominal).copy()
    assert np.max(np.abs(pose_matrix(rc, a, X) - pose_matrix(rb, rb.nominal, Q))) < 1e-14  # zero compliance
    k = 1e-3
    a[rc.index("j2.compliance")] = k
    shifted = Q.copy()
    shifted[:, 1] += k * X[:, 4]
    assert np.max(np.abs(pose_matrix(rc, a, X) - pose_matrix(rb, rb.nominal, shifted))) < 1e-12
    f = jax.jit(lambda p: jc.forward(rc, p, X).p.reshape(-1))
    assert rel_err(np.asarray(jax.jacfwd(f)(jnp.asarray(a))), central_fd(f, a)) < 1e-8  # measured ~1e-10
