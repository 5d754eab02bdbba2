"""How users describe robots (issues 19.1, 21.4, 21.6): standard DH, DH tables with named conventions,
a parent column and transform rows, UR kinematics YAML, URDF <mimic> and joint coupling."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.io import robot_from_dict
from jaxcal.robots.ur import robot_from_ur, ur_dict
from jaxcal.robots.urdf import robot_from_urdf
from jaxcal.robots.urdf_write import robot_urdf_text, urdf_tip_link

DATA = os.path.join(os.path.dirname(jc.__file__), "robots", "data")
KR6 = os.path.join(DATA, "kr6_r900_dh.yaml")
# UR5e standard DH from Universal Robots' published DH parameter table (docs/bibliography.md)
UR5E_DH = {"d1": 0.1625, "a2": -0.425, "a3": -0.3922, "d4": 0.1333, "d5": 0.0997, "d6": 0.0996}
FK_TOL = 1e-12


def _fk_gap(r1, a1, r2, a2, q, q2=None):
    """Largest position (m) and rotation-entry difference of the two robots' tool frames over q (q2 for r2)."""
    f1, f2 = jc.forward(r1, a1, q), jc.forward(r2, a2, q if q2 is None else q2)
    return (float(np.abs(np.asarray(f1.p) - np.asarray(f2.p)).max()),
            float(np.abs(np.asarray(f1.R) - np.asarray(f2.R)).max()))


def _random_q(robot, n, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(robot.q_min, robot.q_max, (n, robot.n_inputs))


# -- the standard DH convention ------------------------------------------------------------------
def test_standard_dh_row_is_the_product_of_four_matrices():
    conv = jc.kin.convention.get_convention("standard_dh")
    theta, d, a, alpha, beta = 0.3, 0.12, -0.4, 0.7, -0.05
    c, s = np.cos, np.sin
    Rz = np.array([[c(theta), -s(theta), 0, 0], [s(theta), c(theta), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    Tz, Tx = np.eye(4), np.eye(4)
    Tz[2, 3], Tx[0, 3] = d, a
    Rx = np.array([[1, 0, 0, 0], [0, c(alpha), -s(alpha), 0], [0, s(alpha), c(alpha), 0], [0, 0, 0, 1]])
    Ry = np.array([[c(beta), 0, s(beta), 0], [0, 1, 0, 0], [-s(beta), 0, c(beta), 0], [0, 0, 0, 1]])
    T = Rz @ Tz @ Tx @ Rx @ Ry
    pose = conv.local_transform(jnp.array([theta - 0.2, d, a, alpha, beta]), 0, jnp.array([0.2]))
    np.testing.assert_allclose(np.asarray(pose.R), T[:3, :3], atol=1e-15)
    np.testing.assert_allclose(np.asarray(pose.p), T[:3, 3], atol=1e-15)
    A, B = conv.motion_split(np.array([theta, d, a, alpha, beta]), 0)
    np.testing.assert_allclose(A @ B, T, atol=1e-15)  # q = 0


def test_standard_dh_robot_gradient_matches_central_differences():
    """d(tool pose)/d(a) of the KR6 table (standard DH + a transform row): jacfwd vs central FD, float64.
    Measured relative error ~1e-10 (h = 1e-6: truncation ~1e-12, rounding ~1e-10)."""
    rb = jc.load_robot(KR6)
    q = _random_q(rb, 4, 3)

    def f(a):
        pose = jc.forward(rb, jnp.asarray(a), q)
        return jnp.concatenate([pose.R.reshape(-1), pose.p.reshape(-1)])

    a0 = np.asarray(rb.nominal_np)
    J = jax.jacfwd(f)(jnp.asarray(a0))
    err = rel_err(J, central_fd(f, a0))
    assert err < 1e-7, err
    jq = jax.jacfwd(lambda qq: jc.forward(rb, rb.nominal, qq).p)(jnp.asarray(q[0]))
    err_q = rel_err(jq, central_fd(lambda qq: jc.forward(rb, rb.nominal, qq).p, q[0]))
    assert err_q < 1e-7, err_q


def _kr6_rows():
    rb = jc.load_robot(KR6)
    doc = yaml.safe_load(open(KR6))
    deg = np.pi / 180
    rows = [(r[3] * deg, r[4] * 1e-3, r[5] * 1e-3, r[6] * deg) for r in doc["joints"][:6]]
    return rb, rows


def test_standard_dh_table_equals_craig_and_khalil_kleinfinger_tables():
    """The same arm as standard DH and as modified DH (Craig letters, and KK letters): row i of the
    modified table takes a, alpha of DH row i-1 and theta, d of DH row i; a last constant row carries
    a6, alpha6; tool frames agree to 1e-12 over 200 random configurations."""
    rb, rows = _kr6_rows()
    craig = [{"name": "A1", "type": "R", "alpha": 0.0, "a": 0.0, "theta": rows[0][0], "d": rows[0][1]}]
    for i in range(1, 6):
        craig.append({"name": f"A{i + 1}", "type": "R", "alpha": rows[i - 1][3], "a": rows[i - 1][2],
                      "theta": rows[i][0], "d": rows[i][1]})
    craig.append({"name": "flange", "type": "F", "alpha": rows[5][3], "a": rows[5][2], "theta": 0.0, "d": 0.0})
    craig.append({"name": "tool", "parent": "flange", "type": "transform", "xyz": [0, 0, 0.05], "rpy": [0, 0, 0]})
    q = _random_q(rb, 200, 5)
    rc = robot_from_dict({"convention": "craig_mdh", "joints": craig}, "craig.yaml")
    kk = [{**{k: v for k, v in r.items() if k not in ("a", "d")}, "d": r["a"], "r": r["d"]} if r["type"] != "transform" else r
          for r in craig]
    rk = robot_from_dict({"convention": "khalil_kleinfinger", "joints": kk}, "kk.yaml")
    for other in (rc, rk):
        dp, dR = _fk_gap(rb, rb.nominal, other, other.nominal, q)
        assert dp < FK_TOL and dR < FK_TOL, (dp, dR)
    assert "A2.a" in rc.names and "A2.r" in rk.names and "A2.alpha" in rb.names


def test_legacy_mdh_files_read_as_before():
    """`convention: mdh` and a `frames:` file without a convention are the seed 001 (KK) layout."""
    st = jc.robots.get("stanford")
    doc = yaml.safe_load(open(os.path.join(DATA, "stanford.yaml")))
    del doc["convention"]
    again = robot_from_dict(doc, "stanford.yaml")
    assert again.names == st.names and np.array_equal(again.nominal_np, st.nominal_np)


# -- round trips ---------------------------------------------------------------------------------
@pytest.mark.parametrize("perturbed", [False, True])
def test_dh_table_to_urdf_and_back_has_identical_kinematics(tmp_path, perturbed):
    """standard DH table -> robot -> URDF -> load -> tool frames equal to 1e-12 over 200 random joint values
    (at the nominal parameters and at a perturbed, 'calibrated' set)."""
    rb = jc.load_robot(KR6)
    a = np.asarray(jc.perturb(rb, 0.01, seed=4)) if perturbed else rb.nominal_np
    path = jc.save_robot(rb, str(tmp_path / "kr6.urdf"), a)
    back = jc.load_robot(path, base="base_link", tip=urdf_tip_link(rb))
    assert back.joint_names == rb.joint_names
    dp, dR = _fk_gap(rb, a, back, back.nominal, _random_q(rb, 200, 7))
    assert dp < FK_TOL and dR < FK_TOL, (dp, dR)


def test_dh_table_yaml_round_trip(tmp_path):
    rb = jc.load_robot(KR6)
    a = np.asarray(jc.perturb(rb, 0.01, seed=5))
    back = jc.load_robot(jc.save_robot(rb, str(tmp_path / "kr6_cal.yaml"), a))
    assert back.names == rb.names
    np.testing.assert_allclose(back.nominal_np, a, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.q_min, rb.q_min, rtol=0, atol=1e-15)


def test_ur_dh_parameters_to_kinematics_urdf_and_back(tmp_path):
    """UR5e dh_parameters -> robot -> kinematics YAML (the UR description's origins: shoulder z = d1, upper
    arm roll pi/2, elbow x = a2, ...) -> robot -> URDF -> robot: tool frames equal to 1e-12."""
    ur = robot_from_ur({"dh_parameters": UR5E_DH}, "ur5e.yaml", "ur5e")
    kin = ur_dict(ur)["kinematics"]
    assert kin["shoulder"]["z"] == pytest.approx(0.1625, abs=1e-15)
    assert kin["upper_arm"]["roll"] == pytest.approx(np.pi / 2, abs=1e-15)
    assert kin["forearm"]["x"] == pytest.approx(-0.425, abs=1e-15)
    assert (kin["wrist_2"]["y"], kin["wrist_3"]["y"]) == pytest.approx((-0.0997, 0.0996), abs=1e-15)
    path = str(tmp_path / "ur5e_calibration.yaml")
    with open(path, "w") as fh:
        yaml.safe_dump({"kinematics": kin}, fh)
    uk = jc.load_robot(path)
    q = _random_q(ur, 200, 8)
    assert max(_fk_gap(ur, ur.nominal, uk, uk.nominal, q)) < FK_TOL
    uu = robot_from_urdf(robot_urdf_text(uk), base="base_link", tip=urdf_tip_link(uk))
    assert uu.joint_names == uk.joint_names
    dp, dR = _fk_gap(uk, uk.nominal, uu, uu.nominal, q)
    assert dp < FK_TOL and dR < FK_TOL
    back = robot_from_ur(ur_dict(ur, form="dh_parameters"), "x.yaml", "ur5e")
    assert np.array_equal(back.nominal_np, ur.nominal_np)


def test_ur_kinematics_yaml_round_trip_is_exact(tmp_path):
    """A calibration file (numbers off the nominal, as ur_calibration writes) -> robot -> file: the same
    numbers and hash; a calibrated robot writes new numbers, a new hash, and reads back to 1e-12."""
    rng = np.random.default_rng(3)
    ur = robot_from_ur({"dh_parameters": UR5E_DH}, "ur5e.yaml", "ur5e")
    kin = ur_dict(ur)["kinematics"]
    for seg in ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"):
        kin[seg] = {k: float(v + 1e-4 * rng.standard_normal()) for k, v in kin[seg].items()}
    kin["hash"] = "calib_4711"
    src = tmp_path / "calibration.yaml"
    src.write_text(yaml.safe_dump({"kinematics": kin}))
    rb = jc.load_robot(str(src))
    out = jc.save_robot(rb, str(tmp_path / "copy.yaml"))
    assert yaml.safe_load(open(out)) == {"kinematics": kin}
    a = np.asarray(jc.perturb(rb, 0.002, seed=1))
    cal = yaml.safe_load(open(jc.save_robot(rb, str(tmp_path / "cal.yaml"), a)))
    assert cal["kinematics"]["hash"] != "calib_4711"
    again = jc.load_robot(str(tmp_path / "cal.yaml"))
    dp, dR = _fk_gap(rb, a, again, again.nominal, _random_q(rb, 100, 2))
    assert dp < FK_TOL and dR < FK_TOL


# -- coupling ------------------------------------------------------------------------------------
MIMIC_URDF = """<robot name="m">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.3"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.2 0 0" rpy="1.5707963267948966 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.25 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/><mimic joint="j2" multiplier="-0.5" offset="0.1"/></joint>
  <joint name="t" type="fixed"><parent link="l3"/><child link="tool"/><origin xyz="0.1 0 0"/></joint>
</robot>"""


def test_urdf_mimic_joint_is_coupled_and_exported():
    rb = robot_from_urdf(MIMIC_URDF)
    assert rb.joint_names == ("j1", "j2")
    np.testing.assert_array_equal(rb.coupling_joint, [[1, 0], [0, 1], [0, -0.5]])
    free = robot_from_urdf(MIMIC_URDF.replace('<mimic joint="j2" multiplier="-0.5" offset="0.1"/>', ""))
    q = _random_q(rb, 50, 1)
    q3 = np.concatenate([q, -0.5 * q[:, 1:2] + 0.1], axis=1)
    assert max(_fk_gap(rb, rb.nominal, free, free.nominal, q, q3)) < FK_TOL
    a = np.asarray(jc.perturb(rb, 0.01, seed=2))
    from jaxcal.robots.urdf import urdf_text

    back = robot_from_urdf(urdf_text(rb, a))
    assert back.joint_names == rb.joint_names
    assert max(_fk_gap(rb, a, back, back.nominal, q)) < FK_TOL


TORSO = {
    "name": "torso_arm", "convention": "standard_dh",
    "columns": ["name", "parent", "type", "theta", "d", "a", "alpha"],
    "joints": [["t1", "base", "R", 0.0, 0.4, 0.1, 0.0],
               ["t2", "t1", "R", 0.2, 0.0, 0.3, 0.0],
               ["t3", "t2", "R", 0.0, 0.0, 0.05, 1.5707963267948966],  # keeps the chest level: q3 = -q1 - q2
               ["s1", "t3", "R", 0.1, 0.2, 0.0, -1.5707963267948966],
               ["s2", "s1", "R", -0.3, 0.0, 0.35, 0.0],
               ["e1", "s2", "R", 0.0, 0.05, 0.3, 1.2]],
    "coupling": {"t3": {"t1": -1, "t2": -1, "offset": 0.0}},
}


def test_coupling_matrix_in_a_robot_table():
    rb = robot_from_dict(TORSO, "torso.yaml")
    assert rb.joint_names == ("t1", "t2", "s1", "s2", "e1")
    assert rb.coupling_joint.shape == (6, 5)
    free = robot_from_dict({**TORSO, "coupling": None}, "free.yaml")
    q = _random_q(rb, 50, 4)
    full = np.concatenate([q[:, :2], -q[:, :1] - q[:, 1:2], q[:, 2:]], axis=1)
    assert max(_fk_gap(rb, rb.nominal, free, free.nominal, q, full)) < FK_TOL
    back = robot_from_dict(jc.robots.robot_to_dict(rb), "again.yaml")
    np.testing.assert_array_equal(back.coupling_joint, rb.coupling_joint)
    off = robot_from_dict({**TORSO, "coupling": {"t3": {"t1": -1, "t2": -1, "offset": 0.25}}}, "off.yaml")
    full_off = full.copy()
    full_off[:, 2] += 0.25
    assert max(_fk_gap(off, off.nominal, free, free.nominal, q, full_off)) < FK_TOL
    again = robot_from_dict(jc.robots.robot_to_dict(off), "again.yaml")
    np.testing.assert_array_equal(again.nominal_np, off.nominal_np)


def test_identify_recovers_the_geometry_of_a_coupled_torso():
    """Position data carry only the 5 independent joints; every robot parameter perturbed (3 mm / 3 mrad
    scale), device frame and marker known (as in test_identify): identify on noise-free data predicts new
    poses to 1e-9 m (the geometry up to the base-set regrouping; the coupled row's parameters are in the
    base set). With the device frame unknown the same fit stops at 7.6 um RMS whether the torso is
    coupled or its third joint is a data column: a start/conditioning matter of the core, not of coupling."""
    rb = robot_from_dict(TORSO, "torso.yaml")
    a_true = np.asarray(jc.perturb(rb, 0.003, seed=6))
    fit = jc.identify(rb, jc.simulate(rb, a_true, _random_q(rb, 60, 1), "position"), known=("dev", "tool"))
    assert fit.converged and fit.rms_after < 1e-6, (fit.converged, fit.rms_after)  # mm
    assert {"t3.d", "t3.a"} & set(fit.estimated)
    q_new = _random_q(rb, 20, 9)
    truth = jc.simulate(rb, a_true, q_new, "position")
    np.testing.assert_allclose(fit.predict(q_new), truth.y, atol=1e-9)


# -- bad input -----------------------------------------------------------------------------------
def _write(tmp_path, text):
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    return str(path)


GOOD = """convention: standard_dh
columns: [name, parent, type, theta, d, a, alpha]
joints:
  - [j1, base, R, 0, 0.4, 0.1, 0]
  - [j2, j1, R, 0, 0, 0.3, 0]
  - [j3, j2, R, 0, 0, 0.2, 0]
"""


@pytest.mark.parametrize("change, message", [
    (("standard_dh", "standard_hd"),
     r"robot.yaml: field 'convention': unknown convention 'standard_hd' \(did you mean 'standard_dh'\?\)"),
    (("theta, d, a, alpha]", "theta, d, alpha]"), r"robot.yaml: field 'columns': missing column\(s\) \['a'\]"),
    (("[j2, j1, R, 0, 0, 0.3, 0]", "[j1, j1, R, 0, 0, 0.3, 0]"),
     r"robot.yaml, row 2 \(line 5\), field 'name': joint 'j1' given twice"),
    (("[j1, base,", "[j1, j3,"),
     r"robot.yaml, field 'parent': the parents form a cycle j1 -> j3 -> j2 -> j1 \(.*robot.yaml, row 1 \(line 4\)\)"),
    (("[j3, j2,", "[j3, j4,"), r"robot.yaml, row 3 \(line 6\), field 'parent': no row named 'j4'"),
    (("0.2, 0]", "zero, 0]"), r"robot.yaml, row 3 \(line 6\), field 'a': not a number: 'zero'"),
    (("0.3, 0]", "0.3]"), r"robot.yaml, row 2 \(line 5\): expected 7 fields"),
    (("type, theta", "type, K, theta"), r"robot.yaml, row 1 \(line 4\): expected 8 fields"),
])
def test_bad_tables_name_file_line_and_field(tmp_path, change, message):
    assert change[0] in GOOD
    path = _write(tmp_path, GOOD.replace(*change))
    with pytest.raises(RobotFileError, match=message):
        jc.load_robot(path)


def test_good_table_loads_and_bad_coupling_is_refused(tmp_path):
    rb = jc.load_robot(_write(tmp_path, GOOD))
    assert rb.joint_names == ("j1", "j2", "j3")
    with pytest.raises(RobotFileError, match=r"coupling', joint 'j3': source 'j4' is not a moving row"):
        jc.load_robot(_write(tmp_path, GOOD + "coupling: {j3: {j4: 1}}\n"))
    with pytest.raises(RobotFileError, match=r"source 'j3' is itself coupled"):
        jc.load_robot(_write(tmp_path, GOOD + "coupling: {j3: {j1: 1}, j2: {j3: 1}}\n"))
    with pytest.raises(RobotFileError, match=r"cal.yaml, field 'kinematics.upper_arm': missing"):
        robot_from_ur({"kinematics": {"shoulder": {"z": 0.1}}}, "cal.yaml")
    with pytest.raises(RobotFileError, match=r"dh_parameters.dd1': unknown key"):
        robot_from_ur({"dh_parameters": {"dd1": 0.1}}, "ur.yaml")
    with pytest.raises(RobotFileError, match="URDF <mimic> takes exactly one source joint"):
        robot_urdf_text(robot_from_dict(TORSO, "torso.yaml"))


@pytest.mark.slow  # 53-84 s here (calibrate + report + plots)
def test_cli_calibrates_a_dh_table_and_writes_the_same_layout(tmp_path):
    """`jaxcal calibrate kr6.yaml data.csv`: the robot argument takes a DH table; the calibrated robot is
    written as a DH table that reproduces the fit."""
    import json

    from jaxcal.cli import main

    rb = jc.load_robot(KR6)
    a_true = jc.perturb(rb, 0.001, seed=3)
    data = jc.simulate(rb, a_true, _random_q(rb, 30, 2), "position", noise=1e-5, seed=1)
    csv = str(tmp_path / "kr6.csv")
    data.to_csv(csv)
    out = tmp_path / "out"
    assert main(["calibrate", KR6, csv, "--out", str(out), "--sigma-position", "1e-5", "-q"]) == 0
    res = json.load(open(out / "results.json"))
    cal = jc.load_robot(str(out / "kr6_r900_dh_calibrated.yaml"))
    a_fit = np.array([p["identified"] for p in res["parameters"][: rb.n_params]])
    q = _random_q(rb, 5, 9)
    np.testing.assert_allclose(jc.forward(cal, cal.nominal, q).p, jc.forward(rb, a_fit, q).p, atol=1e-12)
