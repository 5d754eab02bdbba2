"""Every result carries its health: data mistakes a user makes are reported, not calibrated away silently.
Each case is built the way a careless user would make it (swapped or sign-flipped joint columns, a gross
outlier, degrees given as radians, too few solver steps), with a tracker frame metres away and rotated."""

import numpy as np
import pytest

import jaxcal as jc
from jaxcal.fit import health as hl

SIGMA = 3e-5  # 0.03 mm per axis


@pytest.fixture(scope="module")
def case():
    rb = jc.robots.get("stanford")
    a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=1)
    q = jc.random_configurations(rb, 60, seed=2)
    d = np.zeros(9)
    d[:3], d[3:6] = [1.5, 0.5, 0.3], [0.1, 0.2, 0.4]
    return rb, jc.simulate(rb, a_true, q, "position", noise=SIGMA, device_params=d, seed=3)


def refit(rb, data, q=None, y=None, **kw):
    return jc.identify(rb, jc.Dataset(q=data.q if q is None else q, y=data.y if y is None else y, device="position"),
                       sigma_position=SIGMA, **kw)


def test_clean_data_is_healthy(case):
    rb, data = case
    fit = refit(rb, data)
    assert fit.health.ok, fit.health.warnings
    assert 0.7 < fit.health.residual_ratio < 1.3 and fit.health.rank == len(fit.estimated)
    assert fit.report().startswith("health: ok")


def test_swapped_joint_columns_are_named(case):
    """Columns j2 and j3 swapped: the residual is thousands of times the noise, and the swap is named first."""
    rb, data = case
    q = data.q.copy()
    q[:, [1, 2]] = q[:, [2, 1]]
    h = refit(rb, data, q=q).health
    assert not h.ok and h.residual_ratio > 100
    assert "j2 and j3 look swapped" in h.suspects[0], h.suspects
    assert any("columns j2 and j3" in w for w in h.warnings)


def test_sign_flipped_joint_is_not_silent(case):
    """j4's sign flipped: the geometry absorbs it by turning the joint axis by pi (the readings are then fitted),
    which is no calibration correction: named as an implausible change."""
    rb, data = case
    q = data.q.copy()
    q[:, 3] = -q[:, 3]
    h = refit(rb, data, q=q).health
    assert not h.ok
    assert h.implausible and any(name.startswith(("j4.", "j5.")) for name in h.implausible), h.implausible


def test_gross_outlier_is_flagged_and_can_be_excluded(case):
    """One reading 50 mm off in 60: flagged with its index; outliers='exclude' refits without it to the noise floor."""
    rb, data = case
    y = data.y.copy()
    y[7] += [0.05, 0.0, 0.0]
    flagged = refit(rb, data, y=y)
    assert flagged.health.outliers == (7,) and not flagged.health.ok
    cleaned = refit(rb, data, y=y, outliers="exclude")
    assert cleaned.info["excluded_outliers"] == (7,) and cleaned.health.ok
    assert cleaned.rms_after < 2 * np.sqrt(3) * SIGMA * 1e3


def test_degrees_given_as_radians_are_outside_the_limits(case):
    rb, data = case
    q = data.q.copy()
    q[:, 0] = np.rad2deg(q[:, 0])
    h = refit(rb, data, q=q).health
    assert any(j == "j1" for _, j in h.outside_limits) and not h.ok


def test_unconverged_solver_is_a_warning(case):
    rb, data = case
    h = refit(rb, data, max_steps=2).health
    assert not h.converged and any("without meeting its tolerance" in w for w in h.warnings)


def test_robust_outliers_ignore_gaussian_tails():
    rng = np.random.default_rng(0)
    e = np.linalg.norm(rng.normal(size=(2000, 3)), axis=1)
    assert hl.robust_outliers(e).size == 0
    assert hl.robust_outliers(np.append(e, 50.0)).tolist() == [2000]


def test_cli_exits_1_on_warnings_unless_accepted(tmp_path, capsys):
    """Swapped joint columns through the command line: exit 1, the report's first lines carry the warnings;
    --accept-warnings exits 0 with the same report."""
    from jaxcal.cli import main

    csv = str(tmp_path / "sim.csv")
    assert main(["simulate", "mrr1", "--out", csv, "--n", "40", "--noise-mm", "0.01"]) == 0
    lines = open(csv).read().splitlines()
    head = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    cols = lines[head].split(",")
    i, j = cols.index("j1"), cols.index("j2")
    cols[i], cols[j] = cols[j], cols[i]
    lines[head] = ",".join(cols)
    swapped = tmp_path / "swapped.csv"
    swapped.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert main(["calibrate", "mrr1", str(swapped), "--out", str(out), "--sigma-position", "1e-5", "-q"]) == 1
    report = (out / "report.md").read_text().splitlines()
    assert report[2].startswith("**Health:") and "warning" in report[2]
    assert main(["calibrate", "mrr1", str(swapped), "--out", str(out), "--sigma-position", "1e-5", "-q",
                 "--accept-warnings"]) == 0
