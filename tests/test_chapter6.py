"""Seed 000 chapter 6 Tables 6.7-6.10 and Figure 7.5 as the thesis ran them (issue 20 item 2), through
benchmarks/chapter6.py: MRR-1, Table 6.1 + Table 6.3, one pose at the Table 6.1 joint motions, pose
readings, linear (position) -> GA 50 x 250 seeded from it, fitness limit 1e-5 (eq 5.1a), no polish.

One pose gives 6 equations for 18 redundant parameters (pose Jacobian rank 6): the tip pose is what can be
compared; the parameters differ by null-space moves. The bound used below: the GA stops at fitness
(eq 5.4) <= 1e-5, i.e. ||dp|| + ||dR||_2 <= 1e-5 at the one pose, so the calibrated tip is within 1e-5 m
and 1e-5 of the actual one, and the identifiable (row-space) part of the parameter error is below
1e-5 / sigma_min(J) to first order (sigma_min = 1.32, measured)."""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import chapter6 as c6  # noqa: E402

LIMIT = c6.LIMIT


@pytest.fixture(scope="module")
def thesis():
    rb, a_true, data = c6.thesis_setup()
    return rb, a_true, data, c6.linear_solution(rb, data)


def test_seed_tables_checked_against_each_other():
    """Measured with the engine's kinematics: the nominal tip is Table 6.8's; Table 6.7 is Table 6.1 + Table 6.9
    (angles rad -> deg) to its 5 printed digits; Table 6.8's calibrated vs actual pose is the Figure 6.9 best
    fitness (9.8126e-6 vs 9.8075e-6: the 8-digit matrix entries carry +-5e-9 each). But none of the printed
    error tables reproduces the poses printed with it: Table 6.1 + 6.3 is 5.38 mm from the 6.8 actual tip
    (best of 2304 re-readings of its columns / signs / units 1.47 mm), 6.1 + 6.5 is 0.28 mm from 6.6's
    calibrated tip, 6.1 + 6.9 is 1.65 mm from 6.8's calibrated tip, 6.1 + 6.10 is 7.21 mm from the actual
    tip, against the 1.8 um by which the seed's calibrated tips match its actual one."""
    rb = c6.jc.robots.get("mrr1")
    sc = c6.seed_consistency(rb)
    assert max(sc["nominal_vs_6.8_nominal"]) < 1e-7
    assert sc["6.7_vs_(6.1+6.9)_max_relative"] < 5e-5
    assert sc["6.8_fitness_eq_5.4"] == pytest.approx(c6.FIGURE_6_9["best"], abs=2e-8)
    assert sc["6.8_calibrated_vs_actual"][0] < 2e-6 and sc["6.6_calibrated_vs_actual"][0] < 2e-6
    gaps = {k: sc[k][0] for k in ("6.1+6.3_vs_6.8_actual", "6.1+6.5_vs_6.6_calibrated", "6.1+6.9_vs_6.8_calibrated",
                                  "6.1+6.10_vs_6.8_actual")}
    assert gaps == pytest.approx({"6.1+6.3_vs_6.8_actual": 5.376e-3, "6.1+6.5_vs_6.6_calibrated": 2.805e-4,
                                  "6.1+6.9_vs_6.8_calibrated": 1.650e-3, "6.1+6.10_vs_6.8_actual": 7.206e-3}, rel=2e-3)
    assert sc["6.3_best_rereading_gap_m"] == pytest.approx(1.473e-3, rel=2e-3)


def test_thesis_ga_reproduces_the_table_6_8_pose_not_the_parameters(thesis):
    """Fitness 1.76e-2 nominal -> 4.56e-3 linear (Figure 6.9 starts at 4.5e-3) -> <= 1e-5 at generation 128
    (seed 0; Figure 6.9: ~250). Calibrated tip vs actual: 1.45e-6 m, 7.8e-6 (seed Table 6.8: 1.8e-6 m, 8.0e-6).
    Identified minus true errors: 1.04e-2 in all, 6.4e-6 in the row space of the pose Jacobian (bound
    1e-5 / 1.32 = 7.6e-6), the rest in its 12-dimensional null space: Table 6.7/6.9's parameters are one
    point of a 12-dimensional solution set (ours differ from Table 6.3 by up to 6.5e-3)."""
    rb, a_true, data, a_lin = thesis
    ga = c6.seeded_ga(rb, data, a_lin)
    s = c6.ga_summary(rb, a_true, data, a_lin, ga)
    assert 1.7e-2 < s["fitness_nominal"] < 1.8e-2 and 4.4e-3 < s["fitness_linear"] < 4.7e-3
    assert s["best_final"] <= LIMIT and 50 < s["limit_generation"] <= 250
    dp, dR = s["calibrated_vs_actual"]
    assert dp + dR <= LIMIT
    assert s["pose_jacobian_rank"] == 6
    sigma_min = np.linalg.svd(c6.pose_jacobian(rb, a_true), compute_uv=False)[-1]
    total, row, null = s["dg_minus_true_norm_row_null"]
    assert row < LIMIT / sigma_min and null > 1e-3


def test_level1_mean_tip_is_stable_at_the_measured_pose(thesis):
    """Eq 5.7 on the tip position predicted at the measured pose (the identifiable quantity), L1 = 1e-7 m:
    met after 8 runs (measured); the mean errors predict the actual tip within 0.49 um (each run is within
    eq 5.4's 1e-5; worst run 1.65 um, measured)."""
    rb, a_true, data, a_lin = thesis
    m = c6.level1_summary(rb, a_true, c6.level1(rb, data, a_lin, "tip", 1e-7, 20, data.q))
    assert m["stopped"] and m["runs"] <= 10
    assert m["worst_run_tip_vs_actual_m"] <= LIMIT and m["mean_tip_vs_actual"][0] <= m["worst_run_tip_vs_actual_m"]


def test_figure_7_5_after_reconfiguration():
    """Figure 7.2(b) connection B2-B3-B1, the same modules and errors, the seeded GA: generation 0 best 5.02e-3
    (seed: "about 0.005"), the limit met at generation 141 with 8.74e-6 (seed: ~150, 9.4893e-6), the calibrated
    tip within eq 5.4's bound. The linear solution has each module's values at its rows (linear fitness 5.3e-3 <
    nominal 1.28e-2; in chain order it was 2.46)."""
    f = c6.figure_7_5()
    assert f["robot"] == "mrr1[2-3-1]" and f["fitness_linear"] < f["fitness_nominal"]
    assert 4e-3 < f["best_first"] < 6e-3 and f["best_final"] <= LIMIT and 50 < f["limit_generation"] < 600
    assert sum(f["calibrated_vs_actual"]) <= LIMIT


def test_table_6_10_parameter_rule_needs_more_runs_than_the_tip(thesis):
    """Eq 5.7 on the 18 parameters (L1 = 1e-5): the running mean still moves 5.0e-5 at 44 runs (the seed's
    count) and settles after 70 runs (measured, seeds 0, 1000, ...); its mean predicts the actual tip within
    0.18 um, but the mean errors differ from Table 6.3 by up to 6.2e-3 (null space)."""
    rb, a_true, data, a_lin = thesis
    m = c6.level1_summary(rb, a_true, c6.level1(rb, data, a_lin, "parameters", 1e-5, 100))
    assert m["parameter_change_at_44_runs"] > 1e-5 and m["stopped"] and m["runs"] > 44
    assert m["mean_tip_vs_actual"][0] < LIMIT and m["mean_dg_minus_true_norm_row_null"][2] > 1e-3


@pytest.mark.slow  # a study (~29 s in the suite); chapter 6's GA runs fast in test_thesis_ga_reproduces_the_table_6_8_pose...
def test_figure_6_10_larger_populations_and_more_generations_reach_lower_fitness(thesis):
    """Figure 6.10 on the thesis' one pose, random start, 8 runs: median final best 7.2e-8 (100 x 1000) and
    6.5e-9 (200 x 1500), measured; the seed printed 1.05e-3 and 1.47e-5 (same ordering, see docs/chapter6.md)."""
    rb, _, data, _ = thesis
    f = c6.figure_6_10(rb, data, settings=("100x1000", "200x1500"))
    assert f["200x1500"]["median"] < f["100x1000"]["median"] < f["100x1000"]["seed"]
    assert f["200x1500"]["median"] < f["200x1500"]["seed"]
