"""k-fold cross-validation for any robot and data (jaxcal.fit.cv, `jaxcal cv`)."""

import json

import numpy as np
import pytest

import jaxcal as jc
from jaxcal.fit.cv import cross_validate, fold_of_samples


def test_repeated_poses_share_a_fold():
    q = np.repeat(np.random.default_rng(0).normal(size=(12, 3)), 3, axis=0)
    fold = fold_of_samples(q, 4, seed=1)
    assert all(len(set(fold[3 * i:3 * i + 3])) == 1 for i in range(12))
    assert sorted(np.bincount(fold)) == [9, 9, 9, 9]
    with pytest.raises(ValueError, match="distinct poses"):
        fold_of_samples(q, 13)


def test_cross_validation_of_a_user_robot_and_the_command(tmp_path):
    """MRR-1 data written to CSV as a user would get it: held-out RMS falls from the frames-only fit to the noise
    (3-D RMS of 0.01 mm per axis: 0.017 mm; bound 0.03), pooled over folds equals the per-fold values; the
    command prints the same and writes JSON."""
    from jaxcal.cli import main

    csv = str(tmp_path / "sim.csv")
    assert main(["simulate", "mrr1", "--out", csv, "--n", "50", "--noise-mm", "0.01"]) == 0
    rb = jc.robots.get("mrr1")
    data = jc.Dataset.from_csv(csv, joints=rb.joint_names)
    res = cross_validate(rb, data, folds=5, sigma_position=1e-5)
    assert res.heldout_before > 10 * res.heldout_after and res.heldout_after < 0.03
    n = np.array([r["samples"] for r in res.per_fold])
    pooled = np.sqrt(np.sum(n * np.array([r["heldout_after"] for r in res.per_fold]) ** 2) / n.sum())
    assert abs(pooled - res.heldout_after) < 1e-9 * res.heldout_after
    out = tmp_path / "cv.json"
    assert main(["cv", "mrr1", csv, "--sigma-position", "1e-5", "--json", str(out), "-q"]) == 0
    assert abs(json.loads(out.read_text())["heldout_after"] - res.heldout_after) < 1e-9


def test_nested_cross_validation_chooses_blind_and_rejects_a_bad_candidate():
    """Nested CV (`nested_cross_validate`) on simulated MRR-1 positions: a candidate that leaves the geometry at
    nominal (device frame only) is never chosen; the chosen one's pooled held-out RMS equals its plain k-fold
    figure on the same folds; corrupting the held-out samples of outer fold 0 by 1 m leaves fold 0's inner scores
    unchanged (no choice sees the held-out fold)."""
    from jaxcal.fit.cv import inner_scores, nested_cross_validate

    rb = jc.robots.get("mrr1")
    a_true = jc.perturb(rb, 1e-3, seed=2)
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 40, seed=3), "position", noise=1e-5, seed=4)
    candidates = {"default": {}, "geometry at nominal": {"free": ()}}
    res = nested_cross_validate(rb, data, candidates, folds=4, inner_folds=3, sigma_position=1e-5)
    assert res.chosen == ("default",) * 4 and all(res.converged)
    assert all(s["geometry at nominal"] > 10 * s["default"] for s in res.inner)
    plain = cross_validate(rb, data, folds=4, sigma_position=1e-5)
    assert abs(res.heldout - plain.heldout_after) < 1e-6 * plain.heldout_after
    np.testing.assert_allclose(res.heldout_errors, plain.heldout_errors, rtol=1e-6)
    fold = fold_of_samples(data.q, 4, seed=0)
    y = np.array(data.y)
    y[fold == 0] += 1.0
    corrupted = jc.Dataset(data.q, y, device=data.device)
    again = inner_scores(rb, corrupted, candidates, fold != 0, inner_folds=3, seed=1, sigma_position=1e-5)
    assert again == pytest.approx(res.inner[0], rel=1e-9)
