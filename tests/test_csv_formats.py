"""CSV measurement formats: FIGAROH layouts read as is, orientation encodings, units, round trip."""

import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxcal as jc

REAL = "/work/shared/data/real"
if not os.path.isdir(REAL):
    REAL = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "real")


@pytest.mark.skipif(not os.path.isdir(REAL), reason="real datasets not present")
@pytest.mark.parametrize("rel, n, n_joints, kind, cov", [
    ("talos/left_arm_mocap.csv", 61, 9, "position", ["time"]),
    ("tiago/qualisys_static_postures.csv", 34, 8, "position", []),
    ("ur10/calibration_pose.csv", 23, 6, "pose", []),
])
def test_figaroh_files_read_as_is(rel, n, n_joints, kind, cov):
    path = os.path.join(REAL, rel)
    d = jc.Dataset.from_csv(path)
    assert len(d) == n and d.q.shape[1] == n_joints and d.device.kind == kind
    assert sorted(d.covariates) == cov
    raw = np.genfromtxt(path, delimiter=",", names=True)
    np.testing.assert_array_equal(d.q[:, 0], raw[d.joint_names[0]])
    if kind == "position":
        np.testing.assert_array_equal(d.y[:, 0], raw["x1"])
    else:  # phix1..phiz1 are roll, pitch, yaw about fixed X, Y, Z (URDF's rpy): R = Rz Ry Rx
        from jaxcal.robots.urdf import rpy_matrix

        R = np.stack([rpy_matrix(r) for r in np.stack([raw["phix1"], raw["phiy1"], raw["phiz1"]], 1)])
        np.testing.assert_allclose(d.y[:, :3, :3], R, atol=1e-14)
        np.testing.assert_array_equal(d.y[:, 2, 3], raw["z1"])


@pytest.mark.skipif(not os.path.isdir(REAL), reason="real datasets not present")
def test_second_marker_and_explicit_joint_order():
    path = os.path.join(REAL, "tiago/qualisys_static_postures.csv")
    raw = np.genfromtxt(path, delimiter=",", names=True)
    joints = ("arm_2_joint", "arm_1_joint")
    d = jc.Dataset.from_csv(path, joints=joints, marker=2)
    np.testing.assert_array_equal(d.y[:, 1], raw["y2"])
    np.testing.assert_array_equal(d.q[:, 0], raw["arm_2_joint"])
    with pytest.raises(jc.DataError, match="marker 7 not found"):
        jc.Dataset.from_csv(path, marker=7)


def _pose_data(n=8):
    rb = jc.robots.get("mrr1")
    q = jc.random_configurations(rb, n, seed=3)
    return rb, jc.simulate(rb, jc.perturb(rb, 0.003, seed=2), q, "pose")


def test_pose_round_trip_in_mm_and_deg(tmp_path):
    rb, data = _pose_data()
    data.covariates["temperature"] = np.linspace(20, 25, len(data))
    prismatic = jc.fit.csvfile.prismatic_joints(rb)
    assert prismatic == ("j3",)
    path = data.to_csv(tmp_path / "poses.csv", length_unit="mm", angle_unit="deg", prismatic=prismatic)
    assert open(path).readline().startswith("# units: length=mm, angle=deg")
    assert open(path).read().splitlines()[1] == "# prismatic: j3"
    written = np.genfromtxt(path, delimiter=",", names=True, skip_header=2)
    np.testing.assert_allclose(written["j3"], data.q[:, 2] * 1e3)  # the prismatic joint in mm
    np.testing.assert_allclose(written["j1"], np.degrees(data.q[:, 0]))
    back = jc.Dataset.from_csv(path)  # units and the prismatic joint from the header lines
    assert back.units == {"length": "mm", "angle": "deg"} and back.device.kind == "pose"
    np.testing.assert_allclose(back.q, data.q, atol=1e-13)
    np.testing.assert_allclose(back.y, data.y, atol=1e-12)
    np.testing.assert_allclose(back.covariates["temperature"], data.covariates["temperature"])
    position_only = jc.Dataset.from_csv(path, device="position")
    np.testing.assert_allclose(position_only.y, data.y[:, :3, 3], atol=1e-13)
    with pytest.raises(jc.DataError, match="header says length=mm but length_unit='m'"):
        jc.Dataset.from_csv(path, length_unit="m")


@pytest.mark.parametrize("encoding", ["rotvec", "quaternion", "matrix"])
def test_rotation_vector_quaternion_and_matrix_columns(tmp_path, encoding):
    rb, data = _pose_data()
    R, p = data.y[:, :3, :3], data.y[:, :3, 3]
    if encoding == "rotvec":
        cols, block = ["rvx", "rvy", "rvz"], Rotation.from_matrix(R).as_rotvec()
    elif encoding == "quaternion":
        xyzw = Rotation.from_matrix(R).as_quat()
        cols, block = ["qw", "qx", "qy", "qz"], np.column_stack([xyzw[:, 3], xyzw[:, :3]])
    else:
        cols, block = [f"r{i}{j}" for i in "123" for j in "123"], R.reshape(-1, 9)
    rows = [",".join(list(rb.joint_names) + ["x", "y", "z"] + cols)]
    rows += [",".join(f"{v:.17g}" for v in r) for r in np.hstack([data.q, p, block])]
    path = tmp_path / "d.csv"
    path.write_text("\n".join(rows) + "\n")
    back = jc.Dataset.from_csv(path, joints=rb.joint_names)
    np.testing.assert_allclose(back.y, data.y, atol=1e-13)
    # a bad orientation on the 3rd data row (line 4) is reported there
    block[2] *= 1.1 if encoding != "rotvec" else 100.0
    rows[3] = ",".join(f"{v:.17g}" for v in np.hstack([data.q[2], p[2], block[2]]))
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(jc.DataError, match="line 4: (quaternion|r11..r33|rotation vector)"):
        jc.Dataset.from_csv(path, joints=rb.joint_names)


def _position_csv(tmp_path, q, p, header="j1,j2,j3,x,y,z", comment=None):
    lines = ([comment] if comment else []) + [header] + [",".join(f"{v:.17g}" for v in r) for r in np.hstack([q, p])]
    path = tmp_path / "pos.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_unit_mistakes_are_detected(tmp_path):
    rb = jc.robots.get("mrr1")
    q = jc.random_configurations(rb, 10, seed=1)
    p = np.asarray(jc.simulate(rb, rb.nominal, q).y)
    q_deg = np.degrees(q)
    q_deg[:, 2] = q[:, 2]  # prismatic joint stays in m
    path = _position_csv(tmp_path, q_deg, p)
    with pytest.raises(jc.DataError, match=r"line \d+, column 'j(1|2)'.*degrees given as radians"):
        jc.Dataset.from_csv(path)
    ok = jc.Dataset.from_csv(path, angle_unit="deg", prismatic=("j3",))  # j3 is a length (m), not an angle
    np.testing.assert_allclose(ok.q, q, atol=1e-12)
    path = _position_csv(tmp_path, q, p * 1e3)
    with pytest.raises(jc.DataError, match="millimetres given as metres"):
        jc.Dataset.from_csv(path)
    path = _position_csv(tmp_path, q, p * 1e3, comment="# units: length=mm")
    np.testing.assert_allclose(jc.Dataset.from_csv(path).y, p, atol=1e-15)
    path = _position_csv(tmp_path, q, p * 1e-3, comment="# units: length=mm")  # metres under a mm header
    with pytest.warns(jc.fit.data.UnitWarning, match="metres given as millimetres"):
        jc.Dataset.from_csv(path)
    path = _position_csv(tmp_path, q * 1e-3, p, comment="# units: angle=deg")
    with pytest.warns(jc.fit.data.UnitWarning, match="radians given as degrees"):
        jc.Dataset.from_csv(path)


@pytest.mark.parametrize("kind,columns", [("theodolite", ("azimuth", "elevation")),
                                          ("theodolite_range", ("azimuth", "elevation", "range")),
                                          ("laser_range", ("range",))])
def test_instrument_readings_round_trip_in_mm_and_deg(tmp_path, kind, columns):
    """Sight angles and ranges are written in the file's angle / length unit, one column each, and read back
    exactly; a range given in mm to a file said to be in m is an error naming its line."""
    rng = np.random.default_rng(0)
    y = np.column_stack([rng.uniform(-1.0, 1.0, 5) if c != "range" else rng.uniform(1.5, 4.0, 5) for c in columns])
    data = jc.Dataset(q=rng.uniform(-1, 1, (5, 6)), y=y, device=kind, joint_names=[f"j{i}" for i in range(1, 7)])
    path = tmp_path / f"{kind}.csv"
    data.to_csv(path, length_unit="mm", angle_unit="deg")
    assert open(path).read().splitlines()[1].split(",")[6:] == list(columns)
    back = jc.Dataset.from_csv(path, device=kind)
    assert np.allclose(back.y, y, rtol=0, atol=1e-14) and np.allclose(back.q, data.q, rtol=0, atol=1e-14)
    if "range" in columns:
        text = open(path).read().replace("length=mm", "length=m")
        (tmp_path / "metres.csv").write_text(text)
        with pytest.raises(jc.DataError, match=r"metres\.csv, line 3.*'range'.*millimetres given as metres"):
            jc.Dataset.from_csv(tmp_path / "metres.csv", device=kind)


def test_markers_of_a_multi_position_dataset_round_trip(tmp_path):
    y = np.random.default_rng(1).uniform(-1, 1, (4, 2, 3))
    data = jc.Dataset(q=np.zeros((4, 3)), y=y, device="multi_position", joint_names=["a", "b", "c"])
    data.to_csv(tmp_path / "m.csv", length_unit="mm")
    assert open(tmp_path / "m.csv").read().splitlines()[1] == "a,b,c,x1,y1,z1,x2,y2,z2"
    assert np.allclose(jc.Dataset.from_csv(tmp_path / "m.csv", device="multi_position").y, y, rtol=0, atol=1e-15)
