"""`jaxcal calibrate` with a validation file, pass/fail thresholds (`--verify`) and the export of the
corrections the data support (>= 2 standard errors), issue 19 item 5."""

import json

import numpy as np
import pytest

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.report.job import supported_corrections, verify

SIGMA = 2e-5
MOVED = {"j1.bx": 0.002, "j2.pitch": 0.004, "j3.roll": -0.003}  # the only errors of the true robot, m and rad


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """MRR-1 whose true geometry differs from nominal in three identifiable entries only; 60 calibration
    samples and 30 validation samples (another session of poses in the same set-up), 0.02 mm noise."""
    folder = tmp_path_factory.mktemp("verify")
    rb = jc.robots.get("mrr1")
    a_true = np.asarray(rb.nominal_np).copy()
    for name, v in MOVED.items():
        a_true[rb.index(name)] += v
    for name, n, seed in (("cal.csv", 60, 1), ("val.csv", 30, 2)):
        d = jc.simulate(rb, a_true, jc.random_configurations(rb, n, seed=seed), "position", noise={"position": SIGMA},
                        seed=seed + 10)
        d.to_csv(folder / name, joints=rb.joint_names)
    return folder, rb, a_true


def _run(folder, out, *extra):
    return main(["calibrate", "mrr1", str(folder / "cal.csv"), "--out", str(folder / out), "--sigma-position", str(SIGMA),
                 "-q", "--validation-data", str(folder / "val.csv"), *extra])


def test_validation_supported_corrections_and_a_passing_verdict(files):
    """The validation file is evaluated, not fitted: nominal 2.4 mm -> calibrated at the noise. Of the five
    estimated robot corrections, the three the truth has are >= 2 standard errors and kept, the two whose truth is
    0 are dropped; the model with only the kept ones predicts held-out samples as well as the full calibration
    (within 20 %). The thresholds pass: exit 0."""
    folder, rb, _ = files
    (folder / "ok.yaml").write_text("max_heldout_rms_mm: 0.1\nmax_validation_rms_mm: 0.1\nmax_condition_number: 1.0e6\n")
    assert _run(folder, "out-ok", "--verify", str(folder / "ok.yaml")) == 0
    res = json.load(open(folder / "out-ok" / "results.json"))
    v = res["validation"]
    assert v["samples"] == 30 and v["before"]["position_mm"] > 1.0 > 0.1 > v["after"]["position_mm"]
    sup = res["supported"]
    assert sorted(sup["kept"]) == sorted(MOVED) and sorted(sup["dropped"]) == ["j2.roll", "j3.pitch"]  # truth: 0
    assert sup["heldout"]["position_mm"] < 1.2 * res["rms"]["heldout"]["position_mm"]["after"]
    verdict = json.load(open(folder / "out-ok" / "verdict.json"))
    assert verdict["pass"] and [c["check"] for c in verdict["checks"]] == [
        "max_heldout_rms_mm", "max_validation_rms_mm", "max_condition_number", "health_ok"]
    cal2 = jc.load_robot(str(folder / "out-ok" / res["supported_file"]))
    kept = {p["name"]: p["identified"] for p in res["parameters"] if p["name"] in sup["kept"]}
    for i, name in enumerate(rb.names):
        expected = kept.get(name, float(rb.nominal_np[i]))
        assert float(cal2.nominal_np[i]) == pytest.approx(expected, abs=1e-12)
    assert "## Corrections the data support" in (folder / "out-ok" / "report.md").read_text()


def test_a_failing_threshold_exits_1_and_names_the_check(files, capsys):
    folder, _, _ = files
    (folder / "strict.yaml").write_text("max_validation_rms_mm: 0.001\n")
    assert _run(folder, "out-strict", "--verify", str(folder / "strict.yaml")) == 1
    verdict = json.load(open(folder / "out-strict" / "verdict.json"))
    failed = [c for c in verdict["checks"] if not c["pass"]]
    assert not verdict["pass"] and [c["check"] for c in failed] == ["max_validation_rms_mm"]
    assert failed[0]["value"] > 0.001
    assert "FAIL (max_validation_rms_mm)" in capsys.readouterr().out


def test_bad_thresholds_are_refused_before_any_work(files, capsys):
    folder, _, _ = files
    (folder / "typo.yaml").write_text("max_heldout_rms: 0.1\n")
    assert _run(folder, "out-typo", "--verify", str(folder / "typo.yaml")) == 2
    err = capsys.readouterr().err
    assert "max_heldout_rms" in err and "max_heldout_rms_mm" in err
    assert not (folder / "out-typo").exists()


def test_verify_fails_on_a_missing_number_and_the_supported_rule_is_two_standard_errors():
    """A threshold whose quantity the run lacks (no held-out samples) fails rather than passes; the supported
    set is exactly the parameters with |change| >= 2 standard errors."""
    summary = {"rms": {"train": {"position_mm": {"after": 0.01}}}, "health": {"ok": True}}
    v = verify(summary, {"max_heldout_rms_mm": 1.0, "max_train_rms_mm": 0.1})
    assert not v["pass"] and [c["pass"] for c in v["checks"]] == [False, True, True]
    with pytest.raises(ValueError, match="finite number"):
        verify(summary, {"max_train_rms_mm": float("nan")})

    class Fit:  # the three attributes supported_corrections reads
        robot = jc.robots.get("mrr1")
        a = np.asarray(robot.nominal_np) + np.where(np.arange(18) < 3, 1e-3, 1e-5)
        std_errors = {"j1.bx": 4e-4, "j1.by": 6e-4, "j1.bz": 1e-4, "j2.bx": 4e-6, "dev.x": 1e-9}

    a, kept, dropped = supported_corrections(Fit)
    assert kept == ["j1.bx", "j1.bz", "j2.bx"] and dropped == ["j1.by"]
    changed = np.flatnonzero(a != Fit.robot.nominal_np)
    assert [Fit.robot.names[i] for i in changed] == kept
