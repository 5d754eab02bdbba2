"""`jaxcal calibrate` of the UR10 (a URDF built-in) twice, with `--export urdf-rising,pal-yaml` and `--archive`, and
`jaxcal compare` of the two runs; the interactive report.html and compare.html rendered in headless Chromium
(skipped without `chromium` on PATH): the script ran, one chart marker per sample, the tables sort, a screenshot."""

import json
import os
import shutil
import subprocess

import numpy as np
import pytest
import yaml
from lxml import html as lhtml

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.robots.exports import read_rising
from jaxcal.robots.urdf import robot_from_urdf

CHROMIUM = shutil.which("chromium")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not on PATH (apt-get install chromium)")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two calibrations of one 24-sample UR10 dataset (held-out splits of seeds 0 and 1), both archived,
    and their comparison page."""
    folder = tmp_path_factory.mktemp("html")
    csv = str(folder / "tiago.csv")
    assert main(["simulate", "ur10", "--out", csv, "--n", "24", "--seed", "4"]) == 0
    for name, seed in (("a", "0"), ("b", "1")):
        rc = main(["calibrate", "ur10", csv, "--out", str(folder / name), "--seed", seed, "--sigma-position", "2e-5",
                   "--export", "urdf-rising,pal-yaml", "--archive", str(folder / "archive"), "--accept-warnings", "-q"])
        assert rc == 0
    assert main(["compare", str(folder / "a"), str(folder / "b"), "--out", str(folder / "compare.html")]) == 0
    return folder


def test_exports_provenance_and_archive(runs):
    """The rising-tag URDF of the real run reproduces the calibrated tool positions to 1e-12 (readings + rising);
    the PAL YAML holds the identified offsets, its >= 2 sigma variant the kept ones only; results.json carries
    provenance; both runs are archived with one index line each."""
    res = json.load(open(runs / "a" / "results.json"))
    rb = jc.robots.get("ur10")
    a_fit = np.array([p["identified"] for p in res["parameters"][: rb.n_params]])
    text = (runs / "a" / "ur10_calibrated_rising.urdf").read_text()
    back = robot_from_urdf(text, base=rb.extras["base_link"], tip=rb.extras["tip_link"])
    rising = read_rising(text)
    q = np.asarray(jc.random_configurations(rb, 5, seed=7))
    q2 = q + np.array([rising[j] for j in rb.joint_names])
    assert np.abs(jc.forward(back, back.nominal, q2).p - jc.forward(rb, a_fit, q).p).max() < 1e-12
    pal = yaml.safe_load((runs / "a" / "ur10_pal_calibration.yaml").read_text())
    pal2 = yaml.safe_load((runs / "a" / "ur10_pal_calibration_2sigma.yaml").read_text())
    kept = set(res["supported"]["kept"])
    for j in rb.joint_names:
        i = rb.index(f"{j}.offset")
        assert pal[f"{j}_offset"] == a_fit[i]
        assert pal2[f"{j}_offset"] == (a_fit[i] if f"{j}.offset" in kept else rb.nominal_np[i])
    assert pal["camera_position_x"] == res["device_params"]["calibrated"]["dev.x"]
    assert {"ur10_calibrated_rising_2sigma.urdf", "ur10_pal_calibration.yaml"} <= set(res["files"])
    prov = res["provenance"]
    assert prov["inputs"]["data"]["sha256"] and prov["inputs"]["robot"]["sha256"] is None
    assert prov["command_line"][:3] == ["jaxcal", "calibrate", "ur10"] and len(prov["config_hash"]) == 64
    assert res["identifiability"]["observability"]["O5"] > 0
    index = [json.loads(x) for x in (runs / "archive" / "index.jsonl").read_text().splitlines()]
    assert len(index) == 2 and all((runs / "archive" / e["folder"] / "report.html").is_file() for e in index)
    assert index[0]["heldout_rms_mm"] == res["rms"]["heldout"]["position_mm"]["after"]


def _chromium(url, tmp_path, *args):
    """Run headless Chromium on a file URL (a fresh profile, no network services); its stdout."""
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'profile'}", *args, url]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=True).stdout


def _column(doc, table_id, key):
    """The sort values (data-v; None for n/a) of one column of a table, in row order."""
    table = doc.get_element_by_id(table_id)
    col = [th.get("data-key") for th in table.findall("thead/tr/th")].index(key)
    return [None if tr[col].get("data-v") is None else float(tr[col].get("data-v")) for tr in table.findall("tbody/tr")]


def _descending(values):
    nums = [v for v in values if v is not None]
    return nums == sorted(nums, reverse=True) and values[: len(nums)] == nums  # n/a last


@needs_chromium
def test_report_in_headless_chromium(runs, tmp_path):
    """The script ran (data-ready), drew one marker per sample and split in each of the two series (nominal,
    calibrated), four legend entries, and `?sort=abs_z&dir=desc` sorted the parameter table; a screenshot."""
    url = (runs / "a" / "report.html").as_uri()
    doc = lhtml.fromstring(_chromium(url + "?sort=abs_z&dir=desc", tmp_path, "--dump-dom"))
    assert doc.body.get("data-ready") == "1"
    res = json.load(open(runs / "a" / "results.json"))
    for split in ("train", "heldout"):
        for kind in ("before", "after"):
            marks = doc.xpath(f"//*[@class='pt' and @data-split='{split}' and @data-kind='{kind}']")
            assert len(marks) == res["samples"][split] and len(marks) == len(res["per_sample_errors_mm"][split][kind])
    assert len(doc.xpath("//div[@id='legend']/button")) == 4
    assert doc.get_element_by_id("params").get("data-sorted") == "abs_z:desc"
    assert _descending(_column(doc, "params", "abs_z"))
    shot = tmp_path / "report.png"
    _chromium(url, tmp_path, f"--screenshot={shot}", "--window-size=1200,1800")
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size > 20_000
    if os.environ.get("JAXCAL_SCREENSHOT_DIR"):  # to look at it
        shutil.copy(shot, os.environ["JAXCAL_SCREENSHOT_DIR"])


@needs_chromium
def test_compare_in_headless_chromium(runs, tmp_path):
    url = (runs / "compare.html").as_uri()
    doc = lhtml.fromstring(_chromium(url + "?sort=abs_z&dir=desc", tmp_path, "--dump-dom"))
    assert doc.body.get("data-ready") == "1"
    values = _column(doc, "diffs", "abs_z")
    n_params = len(json.load(open(runs / "a" / "results.json"))["parameters"])
    assert len(values) == n_params and any(v is not None for v in values) and _descending(values)
    shot = tmp_path / "compare.png"
    _chromium(url, tmp_path, f"--screenshot={shot}", "--window-size=1200,1800")
    assert shot.stat().st_size > 10_000
    if os.environ.get("JAXCAL_SCREENSHOT_DIR"):
        shutil.copy(shot, os.environ["JAXCAL_SCREENSHOT_DIR"])
