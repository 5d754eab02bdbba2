"""Bad input to every reader (robot YAML, URDF, CSV, job config, output paths): an error naming the
place, through the library and through `jaxcal calibrate` (exit code 2, one `error:` line), and
no output file left behind, half-written or not."""

import os

import numpy as np
import pytest
from helpers import TWO_JOINT_URDF

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.config import ConfigError, load_config
from jaxcal.robots.io import RobotFileError

GOOD_YAML = """convention: pry
units: {length: m, angle: deg}
joints:
  - [0.5, 0, -0.15, 0, 0, 0, revolute]
  - [0.25, 0, 0, 0, 0, 0, revolute]
  - [0.0, 0, 0, 0, 0, 0, prismatic]
"""
GOOD_URDF = TWO_JOINT_URDF


def _csv_lines(n=12):
    rb = jc.robots.get("mrr1")
    q = jc.random_configurations(rb, n, seed=1)
    y = jc.simulate(rb, jc.perturb(rb, 0.003, seed=2), q).y
    return ["j1,j2,j3,x,y,z"] + [",".join(f"{v:.12g}" for v in r) for r in np.hstack([q, y])]


def _calibrate_fails(capsys, robot, data, out, *extra):
    rc = main(["calibrate", str(robot), str(data), "--out", str(out), "-q", *extra])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert not out.exists() or not os.listdir(out), f"output left behind: {os.listdir(out)}"
    return " ".join(err.split())


# -- robot YAML ------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, where", [
    (lambda s: s.replace("[0.25, 0, 0,", "[0.25, zero, 0,"), r"row 2, field 'y': not a number"),
    (lambda s: s.replace("[0.0, 0, 0, 0, 0, 0, prismatic]", "[0.0, 0, 0, 0, 0, prismatic]"), r"row 3: expected 7 fields"),
    (lambda s: s.replace("revolute]\n  - [0.25", "twisting]\n  - [0.25"), r"row 1, field 'type': unknown joint type"),
    (lambda s: s.replace("convention: pry", "convention: dh"), r"field 'convention': unknown convention 'dh' .*expected one of"),
    (lambda s: s.replace("angle: deg", "angle: grad"), r"units.angle must be 'rad' or 'deg'"),
    (lambda s: s + "  - [0, 0\n", r"not valid YAML"),
])
def test_robot_yaml_errors_name_the_place(tmp_path, capsys, edit, where):
    path = tmp_path / "robot.yaml"
    path.write_text(edit(GOOD_YAML))
    with pytest.raises(RobotFileError, match=where):
        jc.load_robot(str(path))
    data = tmp_path / "d.csv"
    data.write_text("\n".join(_csv_lines()) + "\n")
    err = _calibrate_fails(capsys, path, data, tmp_path / "out")
    assert str(path) in err and "error:" in err


# -- URDF ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, args, where", [
    (lambda s: s.replace("</robot>", ""), (), "malformed XML"),
    (lambda s: s.replace('type="revolute"><parent link="l1"', 'type="ball"><parent link="l1"'), (),
     r"joint\[@name='j2'\]: Invalid joint type: ball"),
    (lambda s: s.replace('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>'), (),
     "<joint name='j2'>/<axis>: axis must be a non-zero vector"),
    (lambda s: s, ("--tip", "gripper"), "tip link 'gripper': no <link name='gripper'>"),
])
def test_urdf_errors_name_the_place(tmp_path, capsys, edit, args, where):
    path = tmp_path / "arm.urdf"
    path.write_text(edit(GOOD_URDF))
    tip = args[1] if args else "tool"
    with pytest.raises(RobotFileError, match=where):
        jc.load_robot(str(path), base="base", tip=tip)
    data = tmp_path / "d.csv"
    data.write_text("j1,j2,x,y,z\n0.1,0.2,0.3,0.1,0.2\n")
    err = _calibrate_fails(capsys, path, data, tmp_path / "out", "--base", "base", "--tip", tip)
    assert str(path) in err and "error:" in err


# -- CSV -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("edit, where", [
    (lambda L: L[:3] + ["0.1,0.2,0.3,nan,0.2,0.3"] + L[3:], r"line 4, column 'x': non-finite value 'nan'"),
    (lambda L: L[:5] + ["0.1,0.2,0.3,0.1,0.2"] + L[5:], r"line 6: 5 fields, header has 6"),
    (lambda L: L[:2] + ["0.1,0.2,0.3,0.1,,0.3"] + L[2:], r"line 3, column 'y': not a number: ''"),
    (lambda L: L[:7] + ["0.1,0.2,0.3,0.1,0.2,1e3"] + L[7:], r"line 8: measured point .* millimetres given as metres"),
    (lambda L: ["j1,j2,x,y,z"] + [r.rsplit(",", 4)[0] + "," + ",".join(r.split(",")[3:]) for r in L[1:]],
     r"missing column\(s\) \['j3'\]"),
    (lambda L: ["# units: length=inch"] + L, r"line 1: length unit must be one of"),
    (lambda L: L[:1], r"no data rows after the header on line 1"),
])
def test_csv_errors_name_the_place(tmp_path, capsys, edit, where):
    path = tmp_path / "data.csv"
    path.write_text("\n".join(edit(_csv_lines())) + "\n")
    with pytest.raises(jc.DataError, match=where):
        jc.Dataset.from_csv(str(path), joints=("j1", "j2", "j3"))
    err = _calibrate_fails(capsys, "mrr1", path, tmp_path / "out")
    assert str(path) in err


# -- job config ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, text, where", [
    ("job.yaml", "robot: mrr1\nholdout: 1.5\n", r"key 'holdout' must be a number in \[0, 1\), got 1.5"),
    ("job.yaml", "robot: mrr1\nsolvr: lm\n", r"unknown key 'solvr'"),
    ("job.yaml", "robot: mrr1\nunits: {length: inch}\n", r"key 'units.length' must be one of"),
    ("job.yaml", "robot: [mrr1\n", r"not valid YAML"),
    ("job.toml", 'robot = "mrr1"\nholdout = \n', r"not valid TOML: .*line 2"),
    ("job.toml", 'free = "j1.x"\n', r"key 'free' must be a list of parameter names"),
])
def test_config_errors_name_the_place(tmp_path, capsys, name, text, where):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=where):
        load_config(str(path))
    rc = main(["calibrate", "--config", str(path), "-q"])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 2 and str(path) in err


def test_missing_inputs(tmp_path, capsys):
    err = _calibrate_fails(capsys, "no_such_robot", tmp_path / "d.csv", tmp_path / "out")
    assert "no_such_robot: no such robot file, and not a built-in robot" in err
    err = _calibrate_fails(capsys, "mrr1", tmp_path / "d.csv", tmp_path / "out")
    assert f"{tmp_path / 'd.csv'}: no such file" in err
    assert main(["calibrate", "-q"]) == 2
    assert "no robot given" in capsys.readouterr().err


# -- outputs ------------------------------------------------------------------------------------------
def test_never_writes_over_an_input(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    data = out / "results.json"  # a CSV that happens to sit where the results would go
    data.write_text("\n".join(_csv_lines()) + "\n")
    original = data.read_bytes()
    rc = main(["calibrate", "mrr1", str(data), "--out", str(out), "-q"])
    assert rc == 2 and "refusing to overwrite the input file" in capsys.readouterr().err
    assert data.read_bytes() == original and os.listdir(out) == ["results.json"]
    rc = main(["simulate", "mrr1", "--out", str(data)])
    assert rc == 0 and data.read_bytes() != original  # simulate may replace a non-input file...
    robot = tmp_path / "r.yaml"
    robot.write_text(GOOD_YAML)
    rc = main(["simulate", str(robot), "--out", str(robot)])  # ...but never its robot file
    assert rc == 2 and robot.read_text() == GOOD_YAML


def test_a_dataset_owns_its_joint_values():
    """`Dataset` and `simulate` copy the joint values they are given: correcting a logged glitch in data.q (as
    docs/tutorials/delta-theodolite.md writes one in) leaves the caller's configurations, which the next
    simulation may reuse, as they were."""
    rb = jc.robots.get("mrr1")
    q = jc.random_configurations(rb, 5, seed=0)
    kept = q.copy()
    data = jc.simulate(rb, rb.nominal, q, "position")
    data.q[2, 0] += np.pi / 2
    jc.Dataset(q=q, y=data.y).q[0, 0] = 9.0
    np.testing.assert_array_equal(q, kept)


def test_failure_while_writing_leaves_nothing(tmp_path):
    from jaxcal.report.job import run_job, write_job

    rb = jc.robots.get("mrr1")
    a = jc.perturb(rb, 0.002, seed=1)
    data = jc.simulate(rb, a, jc.random_configurations(rb, 40, seed=2), noise=1e-5)
    job = run_job(rb, data, holdout=0.25, sigma_position=1e-5, history=False)
    out = tmp_path / "out"

    def broken_writer(path, a):
        with open(path, "w") as fh:
            fh.write("half a robot")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_job(str(out), job, broken_writer, "robot.yaml")
    assert os.listdir(out) == []  # no plot, no report, no half-written robot, no staging folder
    written = write_job(str(out), job)
    assert sorted(os.listdir(out)) == sorted(os.path.basename(p) for p in written)
