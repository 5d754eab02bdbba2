"""`jaxcal` subcommands, called in-process through `jaxcal.cli.main`."""

import json
import os

import numpy as np
import pytest

import jaxcal as jc
from jaxcal.cli import main


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """40 MRR-1 position samples in mm / deg, written by `jaxcal simulate`, and the truth."""
    folder = tmp_path_factory.mktemp("sim")
    csv, truth = str(folder / "mrr1.csv"), str(folder / "truth.json")
    rc = main(["simulate", "mrr1", "--out", csv, "--truth", truth, "--n", "40", "--length-unit", "mm", "--angle-unit", "deg",
               "--perturb-mm", "2", "--noise-mm", "0.01", "--temperature", "--seed", "3"])
    assert rc == 0
    return folder, csv, json.load(open(truth))


def test_simulate_writes_the_stated_units(simulated):
    folder, csv, truth = simulated
    data = jc.Dataset.from_csv(csv)
    assert data.units == {"length": "mm", "angle": "deg"} and len(data) == 40 and "temperature" in data.covariates
    rb = jc.robots.get("mrr1")
    # the readings are the perturbed robot's tool positions (device frame = base, marker at the flange) plus 0.01 mm noise
    clean = jc.simulate(rb, np.asarray(truth["a_true"]), data.q)
    assert np.sqrt(np.mean((data.y - clean.y) ** 2)) < 3e-5


def test_calibrate_builtin_robot(simulated, capsys):
    folder, csv, truth = simulated
    out = folder / "out"
    rc = main(["calibrate", "mrr1", csv, "--out", str(out), "--sigma-position", "1e-5", "-q"])
    assert rc == 0
    res = json.load(open(out / "results.json"))
    assert res["samples"] == {"total": 40, "train": 30, "heldout": 10}
    held = res["rms"]["heldout"]["position_mm"]
    assert held["after"] < 0.05 < 0.5 < held["before"], held  # 2 mm errors, 0.01 mm noise
    assert res["heldout_verdict"].startswith("Held-out error reduced by")
    for name in res["files"]:
        assert (out / name).stat().st_size > 0
    assert not [f for f in os.listdir(out) if f.startswith(".")], "staging files left behind"
    # standard errors are reported for every estimated parameter
    est = [p for p in res["parameters"] if p["status"] == "estimated"]
    assert est and all(p["std_error"] is not None and p["std_error"] > 0 for p in est)
    html = (out / "report.html").read_text()
    assert "<table>" in html and '<img src="error_map.png"' in html
    report = (out / "report.md").read_text()
    for section in ("Errors before and after", "Identifiability", "Parameters", "errors_per_pose.png", "error_map.png"):
        assert section in report
    # the calibrated YAML reproduces the fitted model
    rb = jc.robots.get("mrr1")
    cal = jc.load_robot(str(out / "mrr1_calibrated.yaml"))
    a_fit = np.array([p["identified"] for p in res["parameters"][: rb.n_params]])
    q = jc.random_configurations(rb, 5, seed=9)
    np.testing.assert_allclose(jc.forward(cal, cal.nominal, q).p, jc.forward(rb, a_fit, q).p, atol=1e-12)
    assert "held-out (10 samples)" in capsys.readouterr().out


def test_config_file_with_command_line_override(simulated):
    from jaxcal.config import load_config

    folder, csv, _ = simulated
    cfg = folder / "job.toml"
    cfg.write_text('robot = "mrr1"\ndata = "mrr1.csv"\nout = "cfg-out"\nholdout = 0.25\nsigma_position = 1e-5\n'
                   '[units]\nlength = "mm"\nangle = "deg"\n')
    assert main(["calibrate", "--config", str(cfg), "--seed", "1", "-q"]) == 0
    res = json.load(open(folder / "cfg-out" / "results.json"))  # "out" is relative to the config file
    assert res["seed"] == 1 and res["holdout"] == 0.25 and res["samples"]["heldout"] == 10
    assert res["rms"]["heldout"]["position_mm"]["after"] < 0.05
    yml = folder / "job.yaml"
    yml.write_text("robot: mrr1\ndata: mrr1.csv\nout: cfg-out\nholdout: 0.25\nsigma_position: 1.0e-5\n"
                   "units: {length: mm, angle: deg}\n")
    assert load_config(str(yml)) == load_config(str(cfg))


def test_identifiable_matches_the_library(tmp_path, capsys):
    path = tmp_path / "ident.json"
    assert main(["identifiable", "mrr1", "--method", "location", "--json", str(path), "-q"]) == 0
    got = json.load(open(path))
    ref = jc.identifiable(jc.robots.get("mrr1"), "location")
    assert got["count"] == ref.count and tuple(got["names"]) == ref.names
    assert f"{ref.count} identifiable parameters" in capsys.readouterr().out


def test_bench_quick(tmp_path):
    path = tmp_path / "bench.json"
    assert main(["bench", "--robot", "mrr1", "--n-fk", "200", "--n-fit", "30", "--repeats", "2", "--json", str(path), "-q"]) == 0
    res = json.load(open(path))
    assert res["fk"]["configs_per_s"] > 0 and res["fk"]["compile_s"] > 0
    assert res["identify"]["rms_after_mm"] < 0.05  # 1e-5 m noise, 1 mm errors
    assert main(["bench", "--script", "no_such_benchmark", "-q"]) == 2


def test_diagnose_without_the_gap_module_says_so(simulated, capsys, monkeypatch):
    import sys

    folder, csv, _ = simulated
    monkeypatch.setitem(sys.modules, "jaxcal.gap", None)  # as if jaxcal.gap were not installed
    out = folder / "diag-missing"
    assert main(["diagnose", "mrr1", csv, "--out", str(out), "-q"]) == 1
    assert "needs the gap-diagnosis module jaxcal.gap" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow  # the diagnosis fits ten effects over five folds: about 50 s of CPU here
def test_diagnose(simulated, capsys):
    pytest.importorskip("jaxcal.gap")
    folder, csv, _ = simulated
    out = folder / "diag"
    assert main(["diagnose", "mrr1", csv, "--out", str(out), "-q"]) == 0
    d = json.load(open(out / "diagnosis.json"))
    assert d["robot"] == "mrr1" and "verdict" in d
    assert "verdict" in capsys.readouterr().out


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for cmd in ("calibrate", "identifiable", "simulate", "diagnose", "bench", "demo"):
        assert cmd in text


def test_free_accepts_names_and_patterns(tmp_path, capsys):
    from jaxcal.cli import expand_free

    rb = jc.robots.get("mrr1")
    assert expand_free(["j2.*"], rb) == [n for n in rb.names if n.startswith("j2.")]
    assert expand_free([rb.names[3], "j2.*", rb.names[3]], rb)[0] == rb.names[3]
    assert expand_free(None, rb) is None
    with pytest.raises(KeyError, match=r"'k9\.\*' matches no parameter of mrr1"):
        expand_free(["k9.*"], rb)
    data = tmp_path / "d.csv"
    data.write_text("j1,j2,j3,x,y,z\n0.1,0.2,0.1,0.5,0.1,0.2\n0.2,0.1,0.1,0.4,0.1,0.2\n")
    assert main(["calibrate", "mrr1", str(data), "--free", "k9.*", "--out", str(tmp_path / "o"), "-q"]) == 2
    assert "matches no parameter" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_heldout_verdict_flags_a_fit_that_does_not_generalise():
    from jaxcal.report.job import heldout_verdict

    worse = {"rms": {"heldout": {"position_mm": {"before": 4.66, "after": 5.06}}}, "samples": {"train": 17},
             "identifiability": {"estimated": 30}}  # the UR10 file with every parameter (docs/cli.md)
    text = heldout_verdict(worse)
    assert "no better than the nominal one" in text and "30 parameters from 17 samples" in text
    better = dict(worse, rms={"heldout": {"position_mm": {"before": 5.0, "after": 0.5}}})
    assert heldout_verdict(better).startswith("Held-out error reduced by 90%")
    assert heldout_verdict(dict(worse, rms={"train": {}})) is None


def test_bench_runs_a_repository_benchmark_script(capsys):
    import sys

    argv = list(sys.argv)
    assert main(["bench", "--script", "fk", "--", "--max-n", "1000"]) == 0
    out = capsys.readouterr().out
    assert "jax Mcfg/s" in out and "     1000" in out  # one row, N = 1000, checked against numpy inside
    assert sys.argv == argv


def test_calibrated_robot_keeps_the_input_format():
    from jaxcal.cli import calibrated_robot_file

    assert calibrated_robot_file(jc.robots.get("stanford")) == "stanford_calibrated.yaml"
    urdf_builtins = [n for n in jc.robots.available() if jc.robots.get(n).bodies[0].convention == "urdf"]
    for name in urdf_builtins:  # built-ins read from a URDF are written back as URDF
        assert calibrated_robot_file(jc.robots.get(name)).endswith(".urdf")


def test_the_console_command_flushes_its_output_and_keeps_the_exit_code(tmp_path):
    """`jaxcal` (jaxcal.cli:run) ends with os._exit after main: what it printed to a pipe and the file it
    wrote are complete, and the exit code is main's (0 here, 2 for a bad input)."""
    import subprocess
    import sys

    def console(*args):
        code = f"import sys; from jaxcal.cli import run; sys.argv = ['jaxcal', *{list(args)!r}]; run()"
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)

    ok = console("--no-cache", "simulate", "mrr1", "--n", "5", "--out", "s.csv")
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout == "wrote 5 simulated position samples of mrr1 to s.csv\n"
    assert len(jc.Dataset.from_csv(str(tmp_path / "s.csv"))) == 5
    bad = console("--no-cache", "calibrate", "nothere.urdf", "s.csv")
    assert bad.returncode == 2 and bad.stderr.strip().startswith("error: nothere.urdf: no such robot file")
    # a profiler's results are written at exit: under one, the command exits the usual way (atexit handlers run)
    code = ("import atexit, sys; from jaxcal.cli import run; atexit.register(print, 'exit handlers ran'); "
            "sys.argv = ['jaxcal', '--no-cache', 'calibrate', 'nothere.urdf', 's.csv']; {}run()")
    for profiled in (False, True):
        out = subprocess.run([sys.executable, "-c", code.format("sys.setprofile(lambda *a: None); " if profiled else "")],
                             capture_output=True, text=True, cwd=tmp_path, timeout=300)
        assert out.returncode == 2 and ("exit handlers ran" in out.stdout) == profiled
