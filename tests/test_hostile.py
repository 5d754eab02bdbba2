"""Hostile input (issue 15, items 2, 4 and 6): what a careless or malicious user feeds jaxcal, through the
library and through the CLI. Every case asserts the specific clear error (type and message fragment; for the
CLI exit code 2, exactly one `error:` line and no traceback) or the warning, and the fuzz tests assert that
the CSV and URDF readers either parse or raise their own error types, never another exception.

CLI cases fail before any fit (no JIT compile); the one end-to-end calibration uses MRR-1 and 16 samples.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
from helpers import TWO_JOINT_URDF
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxcal as jc
from jaxcal.cli import calibrated_robot_file, load_job_data, main
from jaxcal.config import ConfigError, load_config
from jaxcal.fit.csvfile import DataError, UnitWarning
from jaxcal.io_atomic import OutputError, check_output_dir, replace_folder, safe_filename
from jaxcal.names import UnknownNameError
from jaxcal.robots.io import RobotFileError
from jaxcal.robots.urdf import URDFError, robot_from_urdf

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# -- inputs ---------------------------------------------------------------------------------------------
URDF = TWO_JOINT_URDF
ROBOT_YAML = """name: arm
convention: pry
units: {length: m, angle: deg}
joints:
  - [0.5, 0, -0.15, 0, 0, 0, revolute]
  - [0.25, 0, 0, 0, 0, 0, revolute]
"""
MRR1_YAML = open(os.path.join(ROOT, "jaxcal", "robots", "data", "mrr1.yaml")).read()


def mrr1_rows(n=12, seed=0):
    """n plausible MRR-1 rows j1, j2 (rad), j3 (m, prismatic), x, y, z (m); numbers only, no kinematics."""
    rng = np.random.default_rng(seed)
    q = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(0.02, 0.28, n)])
    p = rng.uniform(-0.6, 0.6, (n, 3)) + [0.0, 0.0, 0.8]
    return np.hstack([q, p])


def csv_text(rows=None, header="j1,j2,j3,x,y,z", pre=(), eol="\n"):
    rows = mrr1_rows() if rows is None else rows
    lines = list(pre) + [header] + [",".join(f"{v:.9g}" for v in r) for r in rows]
    return eol.join(lines) + eol


def read(tmp_path, content, name="data.csv", **kw):
    """Dataset.from_csv of `content` (str or bytes) for MRR-1's joints."""
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    kw.setdefault("joints", ("j1", "j2", "j3"))
    kw.setdefault("prismatic", ("j3",))
    return jc.Dataset.from_csv(str(path), **kw)


def cli_fails(capsys, argv, fragment):
    """`jaxcal argv` exits 2 with exactly one `error:` line on stderr containing `fragment`, and no traceback."""
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert rc == 2, cap.err
    assert "Traceback" not in cap.err + cap.out
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
    assert fragment in lines[0], lines[0]
    return lines[0]


# -- CSV, through the library ----------------------------------------------------------------------------
def _rows_with(i, j, value):
    rows = mrr1_rows().astype(object)
    rows[i, j] = value
    return [",".join(str(v) for v in r) for r in rows]


CSV_ERRORS = [
    ("empty file", b"", {}, "empty file (no header row)"),
    ("only comments", b"# units: length=m\n# nothing else\n", {}, "empty file"),
    ("header only", b"j1,j2,j3,x,y,z\n", {}, "no data rows after the header on line 1"),
    ("blank lines only", b"\n\n  \n", {}, "empty file"),
    ("not UTF-8", csv_text().encode()[:40] + b"\xff\xfe" + csv_text().encode()[40:], {}, "not UTF-8 text (byte 0xff)"),
    ("latin-1 header", "j1,j2,j3,x,y,z,température\n".encode("latin-1") + csv_text().split("\n", 1)[1].encode(), {},
     "line 1: not UTF-8"),
    ("NUL byte", csv_text().encode().replace(b"\n", b"\n\x00", 1), {}, "line 2: NUL byte"),
    ("NaN joint", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(2, 0, "nan")) + "\n", {}, "line 4, column 'j1': non-finite value 'nan'"),
    ("inf reading", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(0, 4, "-inf")) + "\n", {}, "line 2, column 'y': non-finite"),
    ("overflowing number", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(1, 3, "1e400")) + "\n", {}, "non-finite value '1e400'"),
    ("text in a number", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(1, 1, "12deg")) + "\n", {}, "column 'j2': not a number: '12deg'"),
    ("empty field", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(3, 5, "")) + "\n", {}, "line 5, column 'z': not a number: ''"),
    ("too few fields", csv_text().replace("\n", "\n0.1,0.2\n", 2).replace("\n0.1,0.2\n", "\n", 1), {}, "2 fields, header has 6"),
    ("too many fields", csv_text().rstrip("\n") + ",7\n", {}, "7 fields, header has 6"),
    ("duplicate column", csv_text(header="j1,j2,j3,x,y,x"), {}, "duplicate column name(s) ['x']"),
    ("misspelt joint column", csv_text(header="j1,jj2,j3,x,y,z"), {}, "'j2' misspelt as 'jj2'?"),
    ("no position columns", csv_text(header="j1,j2,j3,a,b,c"), {}, "missing column(s) for the measured position"),
    ("unterminated quote", csv_text().replace("\n", '\n"0.1,', 1).replace('"0.1,', '"0.1', 1), {}, "not a CSV row"),
    ("degrees as radians", csv_text(mrr1_rows() * [57.3, 1, 1, 1, 1, 1]), {}, "rad is more than a full turn"),
    ("huge joint value", "j1,j2,j3,x,y,z\n" + "\n".join(_rows_with(0, 1, "1e300")) + "\n", {}, "more than a full turn"),
    ("millimetres as metres", csv_text(mrr1_rows() * [1, 1, 1, 1000, 1000, 1000]), {}, "millimetres given as metres"),
    ("prismatic in mm as m", csv_text(mrr1_rows() * [1, 1, 1000, 1, 1, 1]), {}, "column 'j3': prismatic joint reading"),
    ("degrees beyond tight limits", csv_text(mrr1_rows() * [1, 1.5, 1, 1, 1, 1]), {"limits": {"j2": (-0.06, 0.06)}},
     "column 'j2': reading"),
    ("prismatic mm beyond limits", csv_text(mrr1_rows() * [1, 1, 10, 1, 1, 1]), {"limits": {"j3": (0.0, 0.3)}},
     "millimetres given as metres"),
    ("bad unit line", csv_text(pre=["# units: length=inch"]), {}, "line 1: length unit must be one of"),
    ("unit conflict", csv_text(pre=["# units: angle=deg"]), {"angle_unit": "rad"}, "the header says angle=deg"),
    ("quaternion not unit", "j1,j2,j3,x,y,z,qw,qx,qy,qz\n0.1,0.2,0.1,0.5,0.1,0.9,2,0,0,0\n", {},
     "quaternion (qw, qx, qy, qz) has norm 2"),
    ("not a rotation matrix", "j1,j2,j3,x,y,z," + ",".join(f"r{i}{j}" for i in "123" for j in "123") +
     "\n0.1,0.2,0.1,0.5,0.1,0.9,1,0,0,0,1,0,0,0,-1\n", {}, "is not a rotation matrix"),
    ("rpy in degrees as radians", "j1,j2,j3,x,y,z,phix,phiy,phiz\n0.1,0.2,0.1,0.5,0.1,0.9,90,0,0\n", {},
     "roll/pitch/yaw angle of 90 rad"),
    ("marker not in file", csv_text(), {"marker": 3}, "marker 3 not found"),
]


@pytest.mark.parametrize("content, kw, fragment", [c[1:] for c in CSV_ERRORS], ids=[c[0] for c in CSV_ERRORS])
def test_csv_errors(tmp_path, content, kw, fragment):
    with pytest.raises(DataError) as exc:
        read(tmp_path, content, **kw)
    assert fragment in str(exc.value), str(exc.value)
    assert str(tmp_path / "data.csv") in str(exc.value)


@pytest.mark.parametrize("name, content", [
    ("byte-order mark", b"\xef\xbb\xbf" + csv_text().encode()),
    ("Windows line ends", csv_text(eol="\r\n").encode()),
    ("old Mac line ends", csv_text(eol="\r").encode()),
    ("spaces around fields", csv_text().replace(",", " , ").encode()),
    ("one sample", csv_text(mrr1_rows(1)).encode()),
])
def test_csv_that_must_parse(tmp_path, name, content):
    data = read(tmp_path, content)
    rows = 1 if name == "one sample" else 12
    np.testing.assert_allclose(data.q, mrr1_rows(rows)[:, :3], rtol=1e-8)
    assert data.joint_names == ("j1", "j2", "j3")


@pytest.mark.parametrize("rows, kw, fragment", [
    (mrr1_rows() * [0.01, 0.01, 1, 1, 1, 1], {"angle_unit": "deg"}, "radians given as degrees?"),
    (mrr1_rows() * [1, 1, 1, 1e-3, 1e-3, 1e-3], {"length_unit": "mm"}, "metres given as millimetres?"),
])
def test_csv_unit_warnings(tmp_path, rows, kw, fragment):
    with pytest.warns(UnitWarning, match=re.escape(fragment)):
        read(tmp_path, csv_text(rows), **kw)


def test_csv_folder_instead_of_file(tmp_path):
    (tmp_path / "data.csv").mkdir()
    with pytest.raises(DataError, match="cannot read"):
        jc.Dataset.from_csv(str(tmp_path / "data.csv"))


def test_constant_joint_column_is_a_warning(tmp_path):
    rows = mrr1_rows()
    rows[:, 1] = 0.5
    path = tmp_path / "data.csv"
    path.write_text(csv_text(rows))
    data, found = load_job_data({"data": str(path)}, jc.robots.get("mrr1"))
    assert len(data) == 12 and len(found) == 1 and "joint column 'j2' has the same value in every sample" in found[0]


# -- URDF ------------------------------------------------------------------------------------------------
def _two_parents(s):
    return s.replace("</robot>", '<link name="l2"/><joint name="j3" type="fixed"><parent link="l2"/><child link="tool"/></joint>'
                     '<joint name="j0" type="fixed"><parent link="base"/><child link="l2"/></joint></robot>')


URDF_ERRORS = [
    ("malformed XML", lambda s: s.replace("</robot>", ""), {}, "malformed XML"),
    ("empty text", lambda s: "", {}, "malformed XML"),
    ("external entity", lambda s: '<?xml version="1.0"?><!DOCTYPE r [<!ENTITY x SYSTEM "file:///etc/passwd">]>' +
     s.replace('<link name="base"/>', '<link name="base"/>&x;'), {}, "a DOCTYPE (entity declarations) is not allowed"),
    ("external entity in a name", lambda s: '<!DOCTYPE r [<!ENTITY x SYSTEM "file:///etc/passwd">]>' +
     s.replace('name="two"', 'name="&x;"'), {}, "malformed XML: Attribute references external entity 'x'"),
    ("entity expansion bomb", lambda s: '<!DOCTYPE r [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>' +
     s.replace('name="two"', 'name="&b;"'), {}, "DOCTYPE"),
    ("root is not robot", lambda s: s.replace("<robot", "<robo").replace("</robot>", "</robo>"), {}, "the root element is <robo>"),
    ("duplicate joint name", lambda s: s.replace('joint name="j2"', 'joint name="j1"'), {},
     "line 5: duplicate <joint name='j1'> (first on line 3)"),
    ("duplicate link name", lambda s: s.replace('<link name="tool"/>', '<link name="tool"/><link name="l1"/>'), {},
     "duplicate <link name='l1'>"),
    ("joint without name", lambda s: s.replace('joint name="j2"', "joint"), {}, "<joint> without a name"),
    ("link with two parents", _two_parents, {"base": "base", "tip": "tool"}, "<link name='tool'> has two parents"),
    ("cycle", lambda s: s.replace('<parent link="base"/><child link="l1"/>', '<parent link="tool"/><child link="l1"/>'),
     {"base": "base", "tip": "tool"}, "cycle through links"),
    ("joint onto itself", lambda s: s.replace('<parent link="l1"/><child link="tool"/>', '<parent link="tool"/><child link="tool"/>'),
     {"base": "base", "tip": "tool"}, "cycle through links tool -> tool"),
    ("two roots", lambda s: s.replace('<link name="base"/>', '<link name="base"/><link name="stray"/>'), {"tip": "tool"},
     "give base="),
    ("undefined parent link", lambda s: s.replace('<parent link="l1"/>', '<parent link="nowhere"/>'), {},
     "parent link 'nowhere' is not defined"),
    ("NaN origin", lambda s: s.replace('xyz="0.3 0 0"', 'xyz="nan 0 0"'), {}, "<joint name='j2'>/<origin>: non-finite"),
    ("infinite limit", lambda s: s.replace('lower="-2"', 'lower="-inf"'), {}, "<joint name='j2'>/<limit>: non-finite"),
    ("zero axis", lambda s: s.replace('<axis xyz="0 1 0"/>', '<axis xyz="0 0 0"/>'), {}, "axis must be a non-zero vector"),
    ("unknown joint type", lambda s: s.replace('type="revolute"><parent link="l1"', 'type="ball"><parent link="l1"'), {},
     "Invalid joint type: ball"),
    ("tip not in file", lambda s: s, {"tip": "gripper"}, "tip link 'gripper': no <link name='gripper'>"),
    ("lone surrogate", lambda s: s.replace("two", "t\ud800o"), {}, "not valid text"),
]


@pytest.mark.parametrize("edit, kw, fragment", [c[1:] for c in URDF_ERRORS], ids=[c[0] for c in URDF_ERRORS])
def test_urdf_errors(edit, kw, fragment):
    with pytest.raises(URDFError) as exc:
        robot_from_urdf(edit(URDF), source="arm.urdf", **kw)
    assert fragment in str(exc.value) and "arm.urdf" in str(exc.value), str(exc.value)


@pytest.mark.parametrize("raw, fragment", [
    (URDF.encode("utf-16"), "not UTF-8 text"),
    (URDF.replace("two", "twö").encode("latin-1"), "line 1: not UTF-8 text (byte 0xf6)"),
])
def test_urdf_file_encoding(tmp_path, raw, fragment):
    path = tmp_path / "arm.urdf"
    path.write_bytes(raw)
    with pytest.raises(URDFError, match=re.escape(fragment)):
        jc.load_robot(str(path))


def test_urdf_with_byte_order_mark_loads(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_bytes(b"\xef\xbb\xbf" + URDF.encode())
    assert jc.load_robot(str(path)).joint_names == ("j1", "j2")


# -- robot YAML ------------------------------------------------------------------------------------------
ROBOT_YAML_ERRORS = [
    ("duplicate key", ROBOT_YAML + "convention: mdh\n", "key 'convention' given twice (lines 2 and 7)"),
    ("duplicate joint name", ROBOT_YAML + "joint_names: [shoulder, shoulder]\n", "name 'shoulder' given twice"),
    ("misspelt key", ROBOT_YAML + "joint_name: [a, b]\n", "unknown key 'joint_name' (did you mean 'joint_names'?)"),
    ("non-UTF-8 bytes", ROBOT_YAML.encode() + b"# \xff\xfe\n", "not valid YAML"),
    ("NUL byte", ROBOT_YAML + "\x00\n", "not valid YAML"),
    ("a list, not a mapping", "- convention: pry\n", "expected a mapping at the top level"),
    ("empty file", "", "expected a mapping at the top level"),
    ("infinite length", ROBOT_YAML.replace("[0.25, 0,", "[.inf, 0,"), "row 2, field 'x': non-finite value"),
    ("NaN angle", ROBOT_YAML.replace("0, 0, 0, revolute]\n  - [0.25", "0, .nan, 0, revolute]\n  - [0.25"),
     "row 1, field 'roll': non-finite value"),
]


@pytest.mark.parametrize("text, fragment", [c[1:] for c in ROBOT_YAML_ERRORS], ids=[c[0] for c in ROBOT_YAML_ERRORS])
def test_robot_yaml_errors(tmp_path, text, fragment):
    path = tmp_path / "robot.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(RobotFileError) as exc:
        jc.load_robot(str(path))
    assert fragment in str(exc.value) and str(path) in str(exc.value), str(exc.value)


# -- job files -------------------------------------------------------------------------------------------
JOB_ERRORS = [
    ("job.yaml", "robot: mrr1\nholdout: 0.2\nholdout: 0.3\n", "key 'holdout' given twice (lines 2 and 3)"),
    ("job.toml", 'robot = "mrr1"\nseed = 1\nseed = 2\n', "not valid TOML"),
    ("job.yaml", "robot: mrr1\nholdot: 0.2\n", "unknown key 'holdot' (did you mean 'holdout'?)"),
    ("job.yaml", "robot: mrr1\nfree: [j1.x, j2.x, j1.x]\n", "key 'free': 'j1.x' given twice"),
    ("job.yaml", "robot: mrr1\njoints: [j1, j1, j3]\n", "key 'joints': 'j1' given twice"),
    ("job.yaml", "robot: mrr1\nholdout: .nan\n", "key 'holdout' must be a number in [0, 1)"),
    ("job.yaml", "robot: mrr1\nsigma_position: .inf\n", "key 'sigma_position' must be a positive number"),
    ("job.yaml", b"robot: mrr1\n# \xff\n", "not valid YAML"),
    ("job.yaml", "- robot: mrr1\n", "expected a mapping of option: value"),
    ("job.yaml", "robot: mrr1\nmax_steps: 0\n", "key 'max_steps' must be a positive integer"),
]


@pytest.mark.parametrize("name, text, fragment", JOB_ERRORS, ids=[f"{n}: {f[:30]}" for n, _, f in JOB_ERRORS])
def test_job_file_errors(tmp_path, name, text, fragment):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError) as exc:
        load_config(str(path))
    assert fragment in str(exc.value) and str(path) in str(exc.value), str(exc.value)


def test_job_file_with_byte_order_mark(tmp_path):
    path = tmp_path / "job.toml"
    path.write_bytes(b"\xef\xbb\xbf" + b'robot = "mrr1"\nholdout = 0.5\n')
    assert load_config(str(path))["holdout"] == 0.5


# -- CLI flags and paths: exit 2, one `error:` line, before any fit -----------------------------------------
@pytest.fixture
def files(tmp_path):
    """A valid MRR-1 CSV and robot YAML in tmp_path."""
    (tmp_path / "data.csv").write_text(csv_text())
    (tmp_path / "robot.yaml").write_text(MRR1_YAML)
    return tmp_path


CLI_ERRORS = [
    (["calibrate", "mrr1", "{d}/data.csv", "--holdout", "1.5"], "argument --holdout: expected a number in [0, 1), got '1.5'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--holdout", "nan"], "expected a number in [0, 1), got 'nan'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--sigma-position", "-1"], "expected a positive number, got '-1'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--sigma-position", "inf"], "expected a positive number, got 'inf'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--max-steps", "0"], "expected a positive integer, got '0'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--max-steps", "many"], "expected a positive integer, got 'many'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--solver", "magic"], "argument --solver: invalid choice: 'magic'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--bogus"], "unrecognized arguments: --bogus"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}/o", "--free", "j1.pich"], "'j1.pich' matches no parameter of mrr1 "
     "(did you mean 'j1.pitch'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}/o", "--known", "dve"], "'dve' names no device parameter (did you mean 'dev'"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}/o", "--free", "j1.x", "j1.x"], "--free: 'j1.x' given twice"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}/data.csv"], "output folder is a file"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}/data.csv/sub"], "is a file, not a folder"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "{d}"], "holds the input"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "/proc/jaxcal-out"], "cannot write in /proc"),
    (["calibrate", "mrr1", "{d}/data.csv", "--out", "/"], "root folder"),
    (["calibrate", "mrr1", "{d}", "--out", "{d}/o"], "cannot read"),
    (["calibrate", "{d}/robot.yaml/x.urdf", "{d}/data.csv", "--out", "{d}/o"], "no such robot file"),
    (["simulate", "mrr1", "--out", "{d}/x.csv", "--n", "0"], "argument --n: expected a positive integer, got '0'"),
    (["simulate", "mrr1", "--out", "{d}"], "--out file is a folder"),
    (["simulate", "mrr1", "--out", "{d}/data.csv/x.csv"], "is a file, not a folder"),
    (["simulate", "mrr1", "--out", "{d}/x.csv", "--noise-mm", "-0.1"], "expected a number >= 0"),
    (["identifiable", "mrr1", "--json", "{d}"], "--json file is a folder"),
    (["cv", "mrr1", "{d}/data.csv", "--folds", "1"], "argument --folds: expected an integer >= 2, got '1'"),
    (["cv", "mrr1", "{d}/data.csv", "--json", "/proc/x/cv.json"], "cannot write in /proc"),
    (["diagnose", "mrr1", "{d}/data.csv", "--out", "{d}/data.csv"], "output folder is a file"),
    (["bench", "--json", "{d}"], "--json file is a folder"),
    (["nonsense"], "invalid choice: 'nonsense'"),
]


@pytest.mark.parametrize("argv, fragment", CLI_ERRORS, ids=[" ".join(a[:1] + a[3:5]) for a, _ in CLI_ERRORS])
def test_cli_errors(files, capsys, argv, fragment):
    before = sorted(os.listdir(files))
    cli_fails(capsys, [a.format(d=files) for a in argv], fragment.format(d=files))
    assert sorted(os.listdir(files)) == before  # nothing written, not even an empty output folder


def test_cli_refuses_a_folder_with_other_files(files, capsys):
    out = files / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    cli_fails(capsys, ["calibrate", "mrr1", files / "data.csv", "--out", out],
              "holds files a previous jaxcal run did not write (notes.txt)")
    assert os.listdir(out) == ["notes.txt"]


def test_cli_refuses_the_current_folder(files, capsys, monkeypatch):
    out = files / "out"
    out.mkdir()
    monkeypatch.chdir(out)
    cli_fails(capsys, ["calibrate", "mrr1", files / "data.csv", "--out", "."], "is the current folder")


@pytest.mark.parametrize("rows, fragment", [
    (mrr1_rows(1), "1 sample(s), 1 for the fit"),
    (mrr1_rows(3), "3 sample(s), 2 for the fit"),
    (mrr1_rows() * [57.3, 1, 1, 1, 1, 1], "column 'j1'"),
])
def test_cli_data_refused_before_the_fit(files, capsys, rows, fragment):
    (files / "data.csv").write_text(csv_text(rows))
    cli_fails(capsys, ["calibrate", "mrr1", files / "data.csv", "--out", files / "o", "-q"], fragment)


def test_cli_error_line_escapes_markup_and_newlines(tmp_path, capsys):
    path = tmp_path / "robot.yaml"
    path.write_text(ROBOT_YAML.replace("name: arm", "name: arm\njoint_nams: [1]"))
    data = tmp_path / "d.csv"
    data.write_text(csv_text())
    line = cli_fails(capsys, ["calibrate", path, data, "--out", tmp_path / "o"], "unknown key 'joint_nams'")
    weird = tmp_path / "[bold]x\ny.yaml"
    weird.write_text("- 1\n")
    line = cli_fails(capsys, ["calibrate", weird, data, "--out", tmp_path / "o"], "[bold]x\\ny.yaml")
    assert "expected a mapping" in line


# -- names that become file names, strings that go into HTML -------------------------------------------------
@pytest.mark.parametrize("name", ["../../etc/passwd", "a/b\\c", "x\x00y", "<script>alert(1)</script>", "..", "", " ",
                                  ".hidden", "C:\\robot", "név", "a" * 500])
def test_safe_filename(tmp_path, name):
    safe = safe_filename(name)
    assert re.fullmatch(r"[A-Za-z0-9+-][A-Za-z0-9._+-]*", safe) and len(safe) <= 100, safe
    assert ".." not in safe.split("_") and not safe.startswith(".")
    assert os.path.dirname(os.path.join(str(tmp_path), safe)) == str(tmp_path)


def test_calibrated_robot_file_stays_in_the_folder():
    robot = jc.robots.get("mrr1").replace(name="../../<img src=x onerror=alert(1)>\x00")
    name = calibrated_robot_file(robot)
    assert name == "img_src_x_onerror_alert_1_calibrated.yaml"


def _summary(hostile):
    """A hand-made job summary whose every input string is `hostile`."""
    row = {"name": hostile, "unit": "length", "nominal": 0.1, "identified": 0.11, "change": 0.01, "std_error": 1e-4,
           "status": "estimated"}
    return {"robot": hostile, "data": hostile + "`", "units_in_file": {"length": "m", "angle": "rad"}, "device": "position",
            "samples": {"total": 10, "train": 8, "heldout": 2}, "seed": 0, "health": {"ok": False, "warnings": [hostile]},
            "rms": {"train": {"position_mm": {"before": 1.0, "after": 0.1}}}, "timings_s": {}, "solver": "lm", "iterations": 3,
            "converged": True, "identifiability": {"estimated": 1, "free": 1, "condition_number_scaled": 1.0,
                                                   "undetermined": [hostile], "poorly_determined": [hostile]},
            "parameters": [row]}


@pytest.mark.parametrize("hostile", ["<script>alert(1)</script>", "<img src=x onerror=alert(1)>", "[x](javascript:alert(1))",
                                     "![p](http://evil/x.png)", "a|b\n# heading\n<b>", "&lt;script&gt;"])
def test_report_html_escapes_input_strings(hostile):
    from jaxcal.report.job import job_html, job_markdown

    page = job_html(job_markdown(_summary(hostile), {}, "robot_calibrated.yaml"), f"Calibration report: {hostile}")
    assert not re.search(r"<(script|img|b|a)[\s>]", page), page  # no tag, link or image from the input
    assert "<h1>Calibration report" in page and page.count("<h1>") == 1  # no heading from the input
    assert page.count("<td>") == 3 + 7  # the errors table and one parameter row of 7 cells: no `|` split a cell


# -- outputs replaced as a set ------------------------------------------------------------------------------------
def _writer(names, fail=False):
    def write(stage):
        for n in names:
            (open(os.path.join(stage, n), "w")).write(n)
        if fail:
            raise OSError("disk full")
        json.dump({"files": [n for n in names if n != "results.json"]}, open(os.path.join(stage, "results.json"), "w"))
        return list(names)
    return write


def test_replace_folder_as_a_set(tmp_path):
    out = tmp_path / "out"
    replace_folder(str(out), _writer(["a.png", "old_calibrated.yaml"]))
    assert sorted(os.listdir(out)) == ["a.png", "old_calibrated.yaml", "results.json"]
    check_output_dir(str(out))  # a previous run's folder may be replaced
    replace_folder(str(out), _writer(["a.png", "new_calibrated.yaml"]))
    assert sorted(os.listdir(out)) == ["a.png", "new_calibrated.yaml", "results.json"]  # no stale robot file
    with pytest.raises(OSError, match="disk full"):
        replace_folder(str(out), _writer(["b.png"], fail=True))
    assert sorted(os.listdir(out)) == ["a.png", "new_calibrated.yaml", "results.json"]  # the old set, untouched
    assert sorted(os.listdir(tmp_path)) == ["out"]  # no staging folder left
    (out / "mine.txt").write_text("x")
    with pytest.raises(OutputError, match="mine.txt"):
        check_output_dir(str(out))


SIGTERM_SCRIPT = textwrap.dedent("""
    import os, sys, time
    from jaxcal.io_atomic import cleanup_on_signals, replace_folder
    def write(stage):
        open(os.path.join(stage, "half.png"), "w").write("x")
        print("ready", flush=True)
        time.sleep(120)
        return ["half.png"]
    with cleanup_on_signals():
        replace_folder(sys.argv[1], write)
""")


def test_sigterm_leaves_no_staging_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").write_text('{"files": []}')
    env = dict(os.environ, PYTHONPATH=ROOT, JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, "-c", SIGTERM_SCRIPT, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        assert any("staging" in n for n in os.listdir(tmp_path))
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        proc.kill()
    assert rc == 128 + signal.SIGTERM, proc.stderr.read()
    assert sorted(os.listdir(tmp_path)) == ["out"] and os.listdir(out) == ["results.json"]


# -- typos in parameter-name lists through the library ------------------------------------------------------------
def _data():
    rb = jc.robots.get("mrr1")
    return rb, jc.Dataset(q=mrr1_rows()[:, :3], y=mrr1_rows()[:, 3:], device="position")


@pytest.mark.parametrize("kw, fragment", [
    ({"free": ["j2.yaw", "j2.rol"]}, "free: parameter: unknown name 'j2.rol' (did you mean 'j2.roll'"),
    ({"bounds": {"j1.pitc": (0, 1)}}, "bounds: parameter: unknown name 'j1.pitc' (did you mean 'j1.pitch'"),
])
def test_identify_names_the_closest_parameter(kw, fragment):
    rb, data = _data()
    with pytest.raises(UnknownNameError) as exc:
        jc.identify(rb, data, **kw)
    assert fragment in str(exc.value) and isinstance(exc.value, KeyError)


# -- end to end: a hostile robot name through a real calibration ------------------------------------------------
@pytest.mark.slow  # one MRR-1 fit: about 35 s on the shared machine
def test_calibrate_with_a_hostile_robot_name(tmp_path, capsys):
    hostile = "../../<img src=x onerror=alert(1)>"
    robot_path = tmp_path / "robot.yaml"
    robot_path.write_text(MRR1_YAML.replace("name: mrr1", f"name: '{hostile}'"))
    rb = jc.load_robot(str(robot_path))
    data = jc.simulate(rb, jc.perturb(rb, 0.002, seed=1), jc.random_configurations(rb, 16, seed=2), noise=1e-5)
    csv = tmp_path / "data.csv"
    data.to_csv(str(csv), prismatic=("j3",))
    out = tmp_path / "out"
    out.mkdir()
    (out / "stale_calibrated.yaml").write_text("from an earlier run")
    (out / "results.json").write_text(json.dumps({"files": ["stale_calibrated.yaml"]}))
    rc = main(["calibrate", str(robot_path), str(csv), "--out", str(out), "--max-steps", "20", "--sigma-position", "1e-5",
               "--accept-warnings", "-q"])
    assert rc == 0, capsys.readouterr().err
    files = sorted(os.listdir(out))
    assert "img_src_x_onerror_alert_1_calibrated.yaml" in files and "stale_calibrated.yaml" not in files
    assert sorted(os.listdir(tmp_path)) == ["data.csv", "out", "robot.yaml"]  # nothing outside --out, no staging
    html = (out / "report.html").read_text()
    assert "<img src=x" not in html and "&lt;img src=x onerror=alert(1)&gt;" in html


# -- fuzz: the readers parse or raise their own errors ---------------------------------------------------------
TOKENS = ["j1", "j2", "j3", "x", "y", "z", "x1", "y1", "z1", "phix", "phiy", "phiz", "qw", "qx", "qy", "qz", "time", "0", "1",
          "-0.5", "0.25", "3.5", "90", "1e3", "1e400", "nan", "inf", "", " ", '"', '""', "#", "# units: length=mm, angle=deg",
          "# units: angle=grad", "# prismatic: j3", "\x00", "\ufeff", "é", "\ud800", "\t", ";"]
csv_field = st.one_of(st.sampled_from(TOKENS), st.floats(allow_nan=True).map(repr), st.text(max_size=4))
csv_line = st.lists(csv_field, max_size=8).map(",".join)


@st.composite
def mutated_csv_lines(draw):
    """A valid MRR-1 CSV (1-6 rows) with 0-3 fields replaced by hostile tokens: often still valid."""
    lines = csv_text(mrr1_rows(draw(st.integers(1, 6)), seed=draw(st.integers(0, 9)))).splitlines()
    for _ in range(draw(st.integers(0, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        fields = lines[i].split(",")
        fields[draw(st.integers(0, len(fields) - 1))] = draw(csv_field)
        lines[i] = ",".join(fields)
    return lines


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lines=st.one_of(st.lists(csv_line, max_size=8), mutated_csv_lines()), eol=st.sampled_from(["\n", "\r\n", "\r"]),
       tail=st.one_of(st.just(b""), st.binary(max_size=6)), joints=st.sampled_from([None, ("j1", "j2"), ("j1", "j2", "j3")]))
def test_fuzz_csv_reader(tmp_path_factory, lines, eol, tail, joints):
    path = tmp_path_factory.mktemp("fuzz") / "f.csv"
    path.write_bytes(eol.join(lines).encode("utf-8", "surrogatepass") + tail)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            data = jc.Dataset.from_csv(str(path), joints=joints, prismatic=("j3",))
        except DataError:
            return
    assert len(data) >= 1 and np.isfinite(data.q).all() and np.isfinite(data.y).all()


NAMES = ["base", "l1", "l2", "tool", "j1", "j2", ""]
NUMBERS = ["0 0 0", "0.1 0 0.2", "nan 0 0", "1e999 0 0", "0 0", "a b c", "", "0 0 1"]


@st.composite
def urdf_text(draw):
    """A small URDF from a pool of names, types and numbers: duplicates, cycles, bad values, garbage."""
    links = draw(st.lists(st.sampled_from(NAMES), max_size=5))
    parts = [f'<link name="{n}"/>' for n in links]
    for _ in range(draw(st.integers(0, 5))):
        name, parent, child = draw(st.sampled_from(NAMES)), draw(st.sampled_from(NAMES)), draw(st.sampled_from(NAMES))
        jtype = draw(st.sampled_from(["revolute", "continuous", "prismatic", "fixed", "ball", "floating", ""]))
        limit = draw(st.sampled_from(["", '<limit lower="-1" upper="1" effort="1" velocity="1"/>', '<limit lower="nan" upper="1"/>',
                                      '<limit lower="2" upper="1" effort="1" velocity="1"/>']))
        parts.append(f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
                     f'<origin xyz="{draw(st.sampled_from(NUMBERS))}" rpy="{draw(st.sampled_from(NUMBERS))}"/>'
                     f'<axis xyz="{draw(st.sampled_from(NUMBERS))}"/>{limit}</joint>')
    text = f'<robot name="{draw(st.sampled_from(NAMES))}">' + "".join(parts) + "</robot>"
    if draw(st.booleans()):
        at = draw(st.integers(0, len(text)))
        text = text[:at] + draw(st.text(max_size=5)) + text[at + draw(st.integers(0, 5)):]
    return text


@st.composite
def mutated_urdf(draw):
    """The valid two-joint URDF with 0-3 attribute values replaced from the pools above: often still valid."""
    text = URDF
    slots = ['xyz="0 0 0.2"', 'xyz="0.3 0 0"', 'xyz="0 0 1"', 'xyz="0 1 0"', 'lower="-3"', 'upper="2"', 'type="revolute"',
             'link name="l1"', 'parent link="l1"', 'child link="tool"']
    for _ in range(draw(st.integers(0, 3))):
        slot = draw(st.sampled_from(slots))
        key = slot.split("=")[0]
        value = draw(st.one_of(st.sampled_from(NUMBERS + NAMES + ["continuous", "prismatic", "fixed", "ball", "-1e9", "0"]),
                               st.text(alphabet="0123456789 .-enaif", max_size=8)))
        text = text.replace(slot, f'{key}="{value}"', 1)
    return text


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=st.one_of(urdf_text(), mutated_urdf()), base=st.sampled_from([None, "base", "l1"]),
       tip=st.sampled_from([None, "tool", "l2"]))
def test_fuzz_urdf_reader(text, base, tip):
    try:
        robot = robot_from_urdf(text, base=base, tip=tip, source="fuzz.urdf")
    except URDFError as exc:
        assert "fuzz.urdf" in str(exc)
        return
    assert np.isfinite(np.asarray(robot.nominal_np)).all() and len(robot.bodies) >= 1
