"""Several measurement sessions, the tracker set up anew in each (issue 19 item 3): one device frame per
session, the robot and the marker shared (`jaxcal.measure.sessions`, `jaxcal.fit.sessions`).

Data not shaped to the model: Stanford arm with 1 mm / 1 mrad errors, each session's tracker 1-2 m away
and turned by a uniformly random rotation, 0.03 mm noise per axis."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err
from scipy.spatial.transform import Rotation

import jaxcal as jc
from jaxcal.fit.identify import apply_to_session, residual_weights, residuals
from jaxcal.fit.sessions import readings_for, session_dataset
from jaxcal.kin.rotations import exp_so3
from jaxcal.measure.sessions import Sessions

SIGMA = 3e-5
MARKER = np.array([0.03, -0.02, 0.08])


def _frame(rng):
    t = rng.normal(size=3)
    return np.concatenate([t / np.linalg.norm(t) * rng.uniform(1.0, 2.0), Rotation.random(random_state=rng).as_rotvec()])


def _session(rb, a_true, frame, marker, n, seed, label):
    q = jc.random_configurations(rb, n, seed=seed)
    d = jc.simulate(rb, a_true, q, "position", noise={"position": SIGMA}, device_params=np.concatenate([frame, marker]),
                    seed=seed + 1)
    return d.q, d.y, [label] * n


def _dataset(parts):
    q, y, labels = (np.concatenate(x) for x in zip(*parts))
    return jc.Dataset(q, y, "position", covariates={"session": labels})


def _relative(f0, f1):
    """(translation m, rotation rad) of frame f1 seen from frame f0, both (x, y, z, rx, ry, rz)."""
    R0, R1 = (np.asarray(exp_so3(jnp.asarray(f[3:]))) for f in (f0, f1))
    return R0.T @ (f1[:3] - f0[:3]), Rotation.from_matrix(R0.T @ R1).as_rotvec()


@pytest.fixture(scope="module")
def three_days():
    rb = jc.robots.get("stanford")
    rng = np.random.default_rng(0)
    a_true = jc.perturb(rb, 1e-3, seed=1)
    frames = [_frame(rng) for _ in range(3)]
    train = _dataset([_session(rb, a_true, f, MARKER, 40, 10 * s + 10, f"day{s + 1}") for s, f in enumerate(frames)])
    test = _dataset([_session(rb, a_true, f, MARKER, 20, 10 * s + 15, f"day{s + 1}") for s, f in enumerate(frames)])
    fit = jc.identify(rb, train, sigma_position=SIGMA)
    return rb, a_true, frames, train, test, fit


def test_each_session_gets_its_frame_and_the_robot_is_shared(three_days):
    """Measured: 43 parameters estimated, residual 0.99 x the noise, RMS 0.048 mm and held-out 0.058 mm (the
    noise is 0.052 mm per 3-D point); the frames carry the robot base's regrouped error (1.5 mm) but their poses
    relative to each other are right to 0.05 mm / 0.04 mrad."""
    rb, _, frames, train, test, fit = three_days
    assert isinstance(fit.device, Sessions) and fit.device.labels == ("day1", "day2", "day3")
    assert fit.health.ok and fit.converged, fit.report()
    assert {n for n in fit.estimated if n.startswith("dev.")} >= {f"dev.day{s}.{p}" for s in (1, 2, 3) for p in "xyz"}
    noise_3d = SIGMA * np.sqrt(3)
    assert fit.rms_after < 1.2 * noise_3d * 1e3
    assert fit.rms_on(test) < 1.3 * noise_3d * 1e3
    d = np.asarray(fit.device_params)
    est = [d[fit.device.index[s]][:6] for s in range(3)]
    for s in (1, 2):
        t_true, r_true = _relative(frames[0], frames[s])
        t_est, r_est = _relative(est[0], est[s])
        assert np.linalg.norm(t_est - t_true) < 1e-4 and np.linalg.norm(r_est - r_true) < 1e-4
    rows = fit.info["sessions"]
    assert [r["samples"] for r in rows] == [40, 40, 40] and not any(r["inconsistent"] for r in rows)
    assert rows[1]["frame_offset_m"] == pytest.approx(np.linalg.norm(_relative(frames[0], frames[1])[0]), abs=1e-4)
    assert "sessions: 3 (one device frame each)" in fit.report()


def test_one_frame_for_all_sessions_says_the_model_does_not_fit(three_days):
    """session_params=() forces one tracker frame on three set-ups: the residual is 2.3e4 x the noise (RMS 1.1 m)
    and the health warns; the start does not mistake the mixed frames for a length unit (their best similarity has scale 0.03,
    which looks like inches, but it leaves a misfit as large as the points' spread)."""
    rb, _, _, train, _, _ = three_days
    one = jc.identify(rb, train, sigma_position=SIGMA, session_params=())
    assert not isinstance(one.device, Sessions)
    assert not one.health.ok and one.health.residual_ratio > 1e3


def test_a_session_whose_tracker_moved_is_flagged():
    """Of three sessions, day 2's tracker is knocked 3 mm halfway through: that session's RMS error is several
    times the others' (measured 1.33 mm against 0.28 and 0.28 mm) and the health names it."""
    rb = jc.robots.get("stanford")
    rng = np.random.default_rng(3)
    a_true = jc.perturb(rb, 1e-3, seed=4)
    f1, f2, f3 = _frame(rng), _frame(rng), _frame(rng)
    knocked = f2 + np.array([0.003, 0, 0, 0, 0, 0])
    parts = [_session(rb, a_true, f1, MARKER, 30, 50, "day1"), _session(rb, a_true, f2, MARKER, 15, 60, "day2"),
             _session(rb, a_true, knocked, MARKER, 15, 70, "day2"), _session(rb, a_true, f3, MARKER, 30, 80, "day3")]
    fit = jc.identify(rb, _dataset(parts), sigma_position=SIGMA)
    rows = {r["session"]: r for r in fit.info["sessions"]}
    assert rows["day2"]["inconsistent"] and not rows["day1"]["inconsistent"] and not rows["day3"]["inconsistent"]
    assert any("day2" in w for w in fit.health.warnings)


def test_a_new_session_needs_its_frame_and_its_marker(three_days):
    """The calibrated robot on day 4 (tracker elsewhere, marker put back 0.5 mm off): fitting only the new frame
    leaves the marker's error in the predictions (held-out 0.56 mm, measured); fitting frame and marker predicts
    day 4 at the noise (0.054 mm)."""
    rb, a_true, _, _, _, fit = three_days
    rng = np.random.default_rng(9)
    frame, marker = _frame(rng), MARKER + np.array([0.0005, 0.0, -0.0002])
    q, y, labels = _session(rb, a_true, frame, marker, 30, 90, "day4")
    q_test, y_test, _ = _session(rb, a_true, frame, marker, 30, 95, "day4")
    day4, day4_test = jc.Dataset(q, y, "position"), jc.Dataset(q_test, y_test, "position")
    both = apply_to_session(fit, day4, sigma_position=SIGMA)
    frame_only = apply_to_session(fit, day4, refit=("dev",), sigma_position=SIGMA)
    assert all(n.startswith(("dev.", "tool.")) for n in both.estimated)
    noise_3d = SIGMA * np.sqrt(3) * 1e3
    assert both.rms_on(day4_test) < 1.3 * noise_3d
    assert frame_only.rms_on(day4_test) > 4 * both.rms_on(day4_test)
    with pytest.raises(ValueError, match="day4"):
        fit.errors(jc.Dataset(q, y, "position", covariates={"session": np.array(labels)}))


def test_sessions_residual_jacobian_matches_central_differences():
    """jacfwd of the weighted residuals w.r.t. robot + three sessions' device parameters vs central differences,
    h = 1e-6, float64: relative error < 1e-7 (measured 1e-10); a sample's residual does not depend on the other
    sessions' frames."""
    rb = jc.robots.get("stanford")
    rng = np.random.default_rng(5)
    frames = [_frame(rng) for _ in range(3)]
    data = _dataset([_session(rb, rb.nominal_np, f, MARKER, 3, 100 + s, f"s{s}") for s, f in enumerate(frames)])
    wrapped = session_dataset(data)
    dev = wrapped.device
    d = np.zeros(dev.n_params)
    for s, f in enumerate(frames):
        d[dev.index[s]] = np.concatenate([f, MARKER])
    x = jnp.concatenate([jnp.asarray(jc.perturb(rb, 1e-3, seed=6)), jnp.asarray(d)])
    q, y, w = jnp.asarray(wrapped.q), jnp.asarray(wrapped.y), residual_weights(dev, 1e-3)

    def f(x):
        return residuals(rb, dev, x, q, y, w).ravel()

    J = jax.jacfwd(f)(x)
    assert rel_err(J, central_fd(f, x, h=1e-6)) < 1e-7
    other = np.asarray(J)[:3, rb.n_params + dev.index[1][:6]]  # session s0's samples vs session s1's frame
    assert np.all(other == 0.0)


def test_session_labels_are_checked():
    dev = Sessions.build(jc.make_device("position"), ("a", "b"))
    assert dev.names[:2] == ("dev.a.x", "dev.a.y") and dev.names[-3:] == ("tool.x", "tool.y", "tool.z")
    with pytest.raises(ValueError, match="distinct"):
        Sessions.build(jc.make_device("position"), ("a b", "a_b"))
    with pytest.raises(ValueError, match=r"\['c'\]"):
        readings_for(dev, jc.Dataset(np.zeros((2, 6)), np.zeros((2, 3)), "position", covariates={"session": ["a", "c"]}))


def test_a_session_column_in_the_csv_calibrates_from_the_command_line(tmp_path):
    """`jaxcal calibrate` on a CSV with a `session` column (two trackers 1-2 m apart, mm): one frame per session,
    exit 0, held-out error at the noise, and the report lists the sessions."""
    import json

    from jaxcal.cli import main
    from jaxcal.fit.csvfile import prismatic_joints

    rb = jc.robots.get("stanford")
    rng = np.random.default_rng(11)
    a_true = jc.perturb(rb, 1e-3, seed=12)
    data = _dataset([_session(rb, a_true, _frame(rng), MARKER, 40, 200 + 10 * s, f"cell-{s}") for s in range(2)])
    csv = tmp_path / "two_days.csv"
    data.to_csv(csv, length_unit="mm", joints=rb.joint_names, prismatic=prismatic_joints(rb))
    back = jc.Dataset.from_csv(csv)
    assert list(back.covariates["session"][[0, -1]]) == ["cell-0", "cell-1"] and np.abs(back.y - data.y).max() < 1e-12
    out = tmp_path / "out"
    assert main(["calibrate", "stanford", str(csv), "--out", str(out), "--sigma-position", str(SIGMA), "-q"]) == 0
    res = json.load(open(out / "results.json"))
    assert res["rms"]["heldout"]["position_mm"]["after"] < 1.5 * SIGMA * np.sqrt(3) * 1e3
    assert "sessions: 2 (one device frame each)" in (out / "report.md").read_text()


def test_gap_diagnosis_refuses_mixed_sessions(three_days):
    """The gap model has one device frame: data of several sessions are refused with a message naming them, not
    diagnosed as one set-up (which would read the frames' difference as an unexplained gap)."""
    rb, _, _, train, _, _ = three_days
    with pytest.raises(ValueError, match=r"one measurement session at a time .*day1"):
        jc.gap.diagnose(rb, train)
