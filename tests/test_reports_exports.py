"""Reports and exports of issue 19 item 5 without a calibration: observability indices O1-O5, the rising-tag
URDF and PAL YAML exports, provenance and the run archive, the comparison page and its command-line errors,
and the HTML builders' escaping."""

import json
import os
import shutil
import subprocess
from datetime import datetime, timezone

import numpy as np
import pytest
import yaml

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.fit.identifiable import observability_indices
from jaxcal.report import html as rh
from jaxcal.report import provenance as pv
from jaxcal.robots import exports as ex
from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.urdf import robot_from_urdf


def test_observability_indices_o1_to_o5_by_hand():
    """W (4 x 2) with singular values 3 and 1: O1 = sqrt(3 * 1) / sqrt(4), O2 = 1/3, O3 = 1, O4 = 1^2 / 3,
    O5 = 1 / (1/3 + 1) = 0.75; the older keys are unchanged."""
    W = np.array([[0.0, 3.0], [1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    ind = observability_indices(W)
    expected = {"O1": np.sqrt(3) / 2, "O2": 1 / 3, "O3": 1.0, "O4": 1 / 3, "O5": 0.75, "menq_borm": np.sqrt(3) / 2,
                "condition": 3.0, "min_singular": 1.0, "noise_amplification": 1 / 3}
    assert set(ind) == set(expected)
    for k, v in expected.items():
        assert ind[k] == pytest.approx(v, rel=1e-12), k


# -- exports ------------------------------------------------------------------------------------------------
MIMIC_URDF = """<robot name="two">
  <link name="base"/><link name="l1"/><link name="l2"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.3" rpy="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.4 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/><mimic joint="j1" multiplier="0.5"/></joint>
  <joint name="j3" type="prismatic"><parent link="l2"/><child link="tool"/><origin xyz="0.2 0 0" rpy="0 0 0"/>
    <axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/><calibration rising="9"/></joint>
</robot>"""


def _round_trip(rb, a, q):
    """Max position and rotation differences between the robot at `a` and its rising-tag URDF read back, with
    the rising values added to the joint readings."""
    text = ex.rising_urdf_text(rb, a)
    back = robot_from_urdf(text, base=rb.extras["base_link"], tip=rb.extras["tip_link"])
    rising = ex.read_rising(text)
    q2 = q + np.array([rising[j] for j in rb.joint_names])
    p1, p2 = jc.forward(rb, a, q), jc.forward(back, back.nominal, q2)
    return float(np.abs(p1.p - p2.p).max()), float(np.abs(p1.R - p2.R).max()), text, back


@pytest.mark.parametrize("which", ["tiago_arm", "mimic"])
def test_rising_urdf_round_trip(which):
    """Reading the rising-tag URDF and adding the rising values to the joint readings reproduces the calibrated
    tool poses to 1e-12; the rising values are the offsets; the geometry without them is in the origins (the
    loaded file's offset parameters are 0); a mimic joint has no tag (its offset is in its origin); an earlier
    `<calibration>` tag of a chain joint is replaced."""
    rb = jc.robots.get("tiago_arm") if which == "tiago_arm" else robot_from_urdf(MIMIC_URDF, base="base", tip="tool")
    a = np.array(jc.perturb(rb, {"length": 1e-3, "angle": 2e-3}, seed=1), float)
    if which == "mimic":
        a[rb.index("j2.offset")] = 0.01
        a[rb.index("j3.offset")] = 0.002
    q = np.asarray(jc.random_configurations(rb, 6, seed=2))
    dp, dR, text, back = _round_trip(rb, a, q)
    assert dp < 1e-12 and dR < 1e-12
    enc = ex.encoder_joints(rb)
    assert set(enc) == set(rb.joint_names) and ex.rising_values(rb, a) == {j: a[i] for j, i in enc.items()}
    assert all(back.nominal_np[back.index(f"{j}.offset")] == 0 for j in enc)
    if which == "mimic":
        assert set(enc) == {"j1", "j3"} and ex.read_rising(text)["j3"] == pytest.approx(0.002, abs=1e-15)
        assert text.count('<calibration rising="') == 2


def test_pal_yaml_layout():
    """PAL's flat mapping: camera pose (rotation vector -> URDF roll-pitch-yaw), one `<joint>_offset` per moving
    joint equal to its offset, the tip position; orientation keys only for a pose marker."""
    rb = jc.robots.get("tiago_arm")
    a = np.asarray(jc.perturb(rb, {"length": 1e-3, "angle": 2e-3}, seed=3), float)
    dev = {"dev.x": 0.1, "dev.y": 0.2, "dev.z": 0.3, "dev.rx": 0.0, "dev.ry": 0.0, "dev.rz": 0.3,
           "tool.x": 0.01, "tool.y": 0.02, "tool.z": 0.03}
    doc = yaml.safe_load(ex.pal_yaml_text(rb, a, dev))
    offsets = {k[: -len("_offset")]: v for k, v in doc.items() if k.endswith("_offset")}
    assert offsets == {j: a[rb.index(f"{j}.offset")] for j in rb.joint_names}
    assert (doc["camera_position_x"], doc["camera_position_y"], doc["camera_position_z"]) == (0.1, 0.2, 0.3)
    assert doc["camera_orientation_y"] == pytest.approx(0.3) and abs(doc["camera_orientation_r"]) < 1e-15
    assert (doc["tip_position_x"], doc["tip_position_z"]) == (0.01, 0.03) and "tip_orientation_r" not in doc
    rolled = ex.pal_calibration(rb, a, dict(dev, **{"tool.rx": 0.2, "tool.ry": 0.0, "tool.rz": 0.0}))
    assert rolled["tip_orientation_r"] == pytest.approx(0.2) and abs(rolled["tip_orientation_p"]) < 1e-15


def test_exports_need_a_urdf_robot_and_known_kinds():
    with pytest.raises(RobotFileError, match="needs a robot loaded from a URDF"):
        ex.export_writers(jc.robots.get("mrr1"), ["pal-yaml"])
    with pytest.raises(ValueError, match="unknown kind 'sdf'"):
        ex.export_writers(jc.robots.get("tiago_arm"), ["sdf"])


def test_cli_export_and_archive_errors(tmp_path, capsys):
    """Refused before any fit, exit 2 with one `error:` line: an export of a non-URDF robot, an unknown kind,
    an archive inside the output folder."""
    csv = tmp_path / "d.csv"
    csv.write_text("j1,j2,j3,x,y,z\n" + "0.1,0.2,0.01,1,2,3\n" * 4)
    cases = [(["--export", "pal-yaml"], "needs a robot loaded from a URDF"), (["--export", "sdf"], "urdf-rising, pal-yaml"),
             (["--archive", str(tmp_path / "out" / "arch")], "must lie outside the output folder")]
    for extra, message in cases:
        capsys.readouterr()
        rc = main(["calibrate", "mrr1", str(csv), "--out", str(tmp_path / "out"), "-q", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("error:") == 1 and message in " ".join(err.split()), err


# -- provenance and archive ----------------------------------------------------------------------------------
def test_sha256_and_config_hash(tmp_path):
    import hashlib

    f = tmp_path / "x.bin"
    f.write_bytes(b"abc" * 1000)
    assert pv.sha256_file(str(f)) == hashlib.sha256(b"abc" * 1000).hexdigest()
    assert pv.sha256_file("stanford") is None and pv.sha256_file(None) is None
    h = pv.config_hash({"robot": "r", "seed": 0, "free": ("a", "b"), "out": "x"})
    assert h == pv.config_hash({"free": ["a", "b"], "seed": 0, "robot": "r", "out": "elsewhere"})  # order, out ignored
    assert h == hashlib.sha256(b'{"free":["a","b"],"robot":"r","seed":0}').hexdigest()
    assert h != pv.config_hash({"robot": "r", "seed": 1, "free": ("a", "b")})


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_git_commit(tmp_path, monkeypatch):
    """The commit of a checkout's top folder; None for a folder inside a checkout (a package installed in
    another project), for a plain folder, and without git."""
    repo = tmp_path / "repo"
    (repo / "sub").mkdir(parents=True)
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git[:3] + ["init", "-q"], check=True)
    (repo / "f").write_text("x")
    subprocess.run(git + ["add", "f"], check=True)
    subprocess.run(git + ["commit", "-q", "-m", "m"], check=True)
    head = subprocess.run(git[:3] + ["rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    assert pv.git_commit(str(repo)) == head and len(head) == 40
    assert pv.git_commit(str(repo / "sub")) is None and pv.git_commit(str(tmp_path)) is None
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    assert pv.git_commit(str(repo)) is None


def test_provenance_block(tmp_path):
    f = tmp_path / "data.csv"
    f.write_text("a\n")
    now = datetime(2026, 1, 2, 3, 4, 5, tzinfo=timezone.utc)
    p = pv.provenance({"robot": "stanford", "data": str(f), "config": None}, {"robot": "stanford"}, ["jaxcal", "x"], now)
    assert p["timestamp_utc"] == "20260102T030405Z" and p["command_line"] == ["jaxcal", "x"]
    assert p["inputs"] == {"robot": {"path": "stanford", "sha256": None}, "data": {"path": str(f), "sha256": pv.sha256_file(str(f))}}
    assert p["jaxcal_version"] == jc.__version__ and p["config_hash"] == pv.config_hash({"robot": "stanford"})
    assert {"python", "jax", "numpy", "git_commit"} <= set(p)


def test_archive_never_overwrites(tmp_path):
    """Two archives of one run with the same timestamp and hash: the second gets `-2`, the first is untouched,
    index.jsonl has one line each; no hidden temp folder stays."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").write_text("first")
    summary = {"robot": "r", "data": "d.csv", "rms": {"heldout": {"position_mm": {"after": 0.5}}},
               "provenance": {"timestamp_utc": "20260102T030405Z", "config_hash": "abcdef0123456789"}}
    arch = tmp_path / "arch"
    e1 = pv.archive_run(str(out), str(arch), summary)
    (out / "results.json").write_text("second")
    e2 = pv.archive_run(str(out), str(arch), summary)
    assert os.path.basename(e1) == "20260102T030405Z-abcdef01" and os.path.basename(e2) == "20260102T030405Z-abcdef01-2"
    assert (arch / os.path.basename(e1) / "results.json").read_text() == "first"
    assert (arch / os.path.basename(e2) / "results.json").read_text() == "second"
    lines = [json.loads(x) for x in (arch / "index.jsonl").read_text().splitlines()]
    assert [x["folder"] for x in lines] == [os.path.basename(e1), os.path.basename(e2)]
    assert lines[0] == {"timestamp_utc": "20260102T030405Z", "robot": "r", "data": "d.csv", "heldout_rms_mm": 0.5,
                        "folder": os.path.basename(e1)}
    assert sorted(os.listdir(arch)) == sorted([os.path.basename(e1), os.path.basename(e2), "index.jsonl"])


# -- HTML builders and the comparison ------------------------------------------------------------------------
HOSTILE = "</script><img src=x onerror=alert(1)>"


def _results(robot, values, ses, rms_after):
    params = [{"name": n, "unit": "length", "nominal": 0.0, "identified": v, "change": v, "std_error": s, "status": "estimated"}
              for n, v, s in zip(("p.x", "p.y"), values, ses)]
    return {"robot": robot, "data": HOSTILE, "parameters": params, "samples": {"total": 10},
            "rms": {"train": {"position_mm": {"before": 1.0, "after": rms_after}}}}


def test_json_script_cannot_end_its_element():
    text = rh.json_script({"s": HOSTILE + "&\u2028"})
    assert "<" not in text and ">" not in text and "&" not in text and json.loads(text) == {"s": HOSTILE + "&\u2028"}


def test_parameter_differences_and_z():
    a, b = _results("r", (1.0, 2.0), (0.1, None), 0.1), _results("r", (1.3, 2.5), (0.2, 0.1), 0.2)
    d = rh.parameter_differences(a["parameters"], b["parameters"])
    assert d[0]["diff"] == pytest.approx(0.3) and d[0]["z"] == pytest.approx(0.3 / np.sqrt(0.05))
    assert d[1]["diff"] == pytest.approx(0.5) and d[1]["z"] is None  # run A has no standard error for it
    rows = rh.comparison_rows(a, b)
    assert rows[0] == ["training RMS [mm]", 0.1, 0.2, pytest.approx(0.1)] and rows[1][1:] == [None, None, None]


def test_report_html_escapes_input_strings():
    """A hand-made summary whose strings are markup: nothing of it becomes a tag; one script runs, allowed by
    its hash in the Content-Security-Policy."""
    s = _results(HOSTILE, (1.0, 2.0), (0.1, 0.1), 0.1)
    s["parameters"][0]["name"] = HOSTILE
    s.update(health={"ok": False, "warnings": [HOSTILE]}, per_sample_errors_mm={"train": {"before": [1, 2], "after": [0.1, 0.2]}})
    page = rh.report_html(s, f"# Calibration report: {HOSTILE}")
    assert "<img" not in page and page.count("<script>") == 1 and page.count("<script") == 2
    assert page.count("&lt;img src=x onerror=alert(1)&gt;") >= 4  # title, heading, warning, parameter, markdown
    script = page.split("<script>")[1].split("</script>")[0]
    import base64
    import hashlib

    assert base64.b64encode(hashlib.sha256(script.encode()).digest()).decode() in page.split("</head>")[0]


def test_table_cells_and_sort_values():
    t = rh.table([("n", "name", "text"), ("v", "value", "num")], [["<b>", 1.5], ["x", None], ["y", (2.0, "two")]], "t", True)
    assert "&lt;b&gt;" in t and "<td data-v='1.5'>1.5</td>" in t and "<td>n/a</td>" in t and "<td data-v='2.0'>two</td>" in t
    assert "class='sortable'" in t and "data-key='v' data-type='num'" in t


def _write(folder, doc):
    folder.mkdir()
    (folder / "results.json").write_text(json.dumps(doc))


def test_compare_command(tmp_path, capsys):
    """compare writes the page; a folder without results.json, a broken results.json and runs of different
    robots are refused with exit 2 and one `error:` line naming the file."""
    _write(tmp_path / "a", _results("arm", (1.0, 2.0), (0.1, 0.1), 0.1))
    _write(tmp_path / "b", _results("arm", (1.3, 2.0), (0.2, 0.1), 0.2))
    _write(tmp_path / "c", _results("other", (1.0, 2.0), (0.1, 0.1), 0.1))
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "results.json").write_text("{not json")
    out = tmp_path / "cmp.html"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 0
    page = out.read_text()
    assert "<table id='diffs' class='sortable'>" in page and "1.342" in page and "<img" not in page
    for other, message in (("missing", "missing/results.json: no such file"), ("c", "robot 'other'"),
                           ("d", "d/results.json: not valid JSON")):
        capsys.readouterr()
        rc = main(["compare", str(tmp_path / "a"), str(tmp_path / other), "--out", str(tmp_path / "x.html")])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("error:") == 1 and message in " ".join(err.split()), err
    assert not (tmp_path / "x.html").exists()


def test_quality_rows_health_and_verdict():
    """The quality summary lists every split's RMS, validation, conditioning, O1-O5 (not the duplicate names) and
    a `quality` block; warnings and a failed verdict are shown."""
    s = _results("arm", (1.0, 2.0), (0.1, 0.1), 0.1)
    s["rms"]["heldout"] = {"position_mm": {"before": 2.0, "after": 0.3}, "orientation_mrad": {"before": 4.0, "after": 0.5}}
    s["validation"] = {"samples": 7, "before": {"position_mm": 3.0}, "after": {"position_mm": 0.4}}
    s["identifiability"] = {"estimated": 2, "free": 5, "condition_number_scaled": 12.5,
                            "observability": observability_indices(np.diag([3.0, 1.0]))}
    s["quality"] = {"per_axis": {"heldout": {"x": {"rmse_mm": 0.2, "r2": 0.999999}}}, "correlation_threshold": 0.8,
                    "correlated_pairs": [{"a": "p.x", "b": "p.y", "rho": 0.93}]}
    rows = {r[0]: r[1:] for r in rh.quality_rows(s)}
    assert rows["held-out RMS position [mm]"] == [2.0, 0.3] and rows["held-out RMS orientation [mrad]"] == [4.0, 0.5]
    assert rows["validation RMS position [mm] (7 samples)"] == [3.0, 0.4] and rows["estimated / free parameters"][1] == "2 / 5"
    assert rows["observability O5"][1] == pytest.approx(0.75) and not any("menq" in k for k in rows)
    assert rows["held-out RMSE x [mm] (R\u00b2 0.999999)"][1] == 0.2
    assert rows["parameter pairs with |rho| > 0.8"][1] == "1: p.x ~ p.y +0.930"
    s.update(health={"ok": False, "warnings": ["w1", "w2"]},
             verdict={"pass": False, "checks": [{"check": "max_heldout_rms_mm", "value": 0.3, "threshold": 0.1, "pass": False}]})
    page = rh.report_html(s, "")
    assert "2 warning(s)" in page and "<li>w2</li>" in page and "<p id='verdict' class='bad'>FAIL</p>" in page


# ---- the quality summary (per-axis RMSE, R^2, correlated pairs) -------------------------------------------------------
def test_quality_summary_against_hand_values():
    """A stand-in fit whose predictions miss by (1, -2, 0) mm on x, y, z: RMSE 1, 2, 0 mm and R^2 from the spread
    of the readings; a covariance with rho(a, c) = 0.9 and rho(a, b) = 0.5 lists only (a, c)."""
    from types import SimpleNamespace

    from jaxcal.report.job import axis_quality, correlated_pairs, quality_lines

    y = np.array([[0.0, 0.0, 0.0], [0.01, 0.02, 0.0], [0.02, 0.04, 0.0], [0.03, 0.06, 0.0]])
    data = jc.Dataset(q=np.zeros((4, 6)), y=y, device="position")
    miss = np.array([1e-3, -2e-3, 0.0])
    fit = SimpleNamespace(device=data.device, predict=lambda q: y - miss)
    q = axis_quality(fit, data)
    assert np.isclose(q["x"]["rmse_mm"], 1.0) and np.isclose(q["y"]["rmse_mm"], 2.0) and q["z"]["rmse_mm"] == 0.0
    ss_x = np.sum((y[:, 0] - y[:, 0].mean()) ** 2)
    assert np.isclose(q["x"]["r2"], 1 - 4 * 1e-6 / ss_x) and q["z"]["r2"] is None  # z never moves: R^2 undefined
    sd = np.array([1.0, 2.0, 3.0])
    rho = np.array([[1.0, 0.5, 0.9], [0.5, 1.0, 0.0], [0.9, 0.0, 1.0]])
    cov_fit = SimpleNamespace(covariance=rho * np.outer(sd, sd), estimated=("a", "b", "c"))
    assert correlated_pairs(cov_fit) == [{"a": "a", "b": "c", "rho": pytest.approx(0.9)}]
    lines = quality_lines({"per_axis": {"heldout": q}, "correlated_pairs": correlated_pairs(cov_fit), "correlation_threshold": 0.8})
    assert lines[0].startswith("held-out per axis: x 1 mm") and "a ~ c +0.900" in lines[1]
