"""The calibration core (jaxcal.fit.core): one start and one solve path for identify, the gap baseline,
Monte Carlo and the fleet. Tested on set-ups the model did not shape: a device frame rotated 150 degrees
and metres away, readings in millimetres, folds as sample-weight masks."""

import dataclasses
import time

import numpy as np
import pytest
from conftest import rel_err

import jaxcal as jc
from jaxcal.fit import core
from jaxcal.fit.data import DataError
from jaxcal.gap.baseline import baseline_fits

NOISE = 5e-5  # 0.05 mm and 0.05 mrad per component


def far_frame(device, seed=0):
    """Device parameters: the frame 4 m away and rotated 150 degrees about a generic axis, a 5 cm marker offset."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    d = np.zeros(device.n_params)
    d[:3] = 4.0 * rng.normal(size=3) / np.linalg.norm(rng.normal(size=3))
    d[:3] *= 4.0 / np.linalg.norm(d[:3])
    d[3:6] = np.deg2rad(150.0) * axis / np.linalg.norm(axis)
    d[6:9] = [0.02, -0.03, 0.05]
    return d


@pytest.fixture(scope="module")
def stanford():
    rb = jc.robots.get("stanford")
    return rb, jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=1)


def simulated(rb, a_true, kind, n, seed):
    dev = jc.make_device(kind)
    q = jc.random_configurations(rb, n, seed=seed)
    return jc.simulate(rb, a_true, q, dev, noise={"position": NOISE, "orientation": NOISE}, device_params=far_frame(dev), seed=seed)


def test_registration_recovers_rotation_translation_and_scale():
    """Kabsch / Umeyama: p = s R y + t recovered to 1e-12 from exact points; a reflection is never returned."""
    rng = np.random.default_rng(5)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R *= np.sign(np.linalg.det(R))
    P = rng.normal(size=(20, 3))
    R_fit, t_fit = core.rigid_registration(P, (P - [1.0, 2.0, 3.0]) @ R)  # p = R y + t with y = R^T (p - t)
    assert np.allclose(R_fit, R, atol=1e-12) and np.allclose(t_fit, [1.0, 2.0, 3.0], atol=1e-12)
    s, R_s, _ = core.similarity_registration(P, 1e3 * (P - [1.0, 2.0, 3.0]) @ R)  # readings in mm
    assert abs(s - 1e-3) < 1e-15 and np.allclose(R_s, R, atol=1e-12)
    R_m, _ = core.rigid_registration(P, P * [1.0, 1.0, -1.0])
    assert np.linalg.det(R_m) > 0


def test_registered_frame_of_the_delta_is_exact():
    """Moved from the gap tests: the Delta's registered start recovers a frame 5 cm / 0.05 rad off to 1e-9 from
    noise-free readings of the nominal Delta (the robot parameters stay nominal, the marker offset at zero)."""
    from jaxcal.gap.closed import delta_workspace

    delta = jc.robots.get("delta")
    dev = jc.make_device("position")
    q = delta_workspace(16, seed=9)
    frame = np.array([0.05, -0.03, 0.02, 0.05, -0.02, 0.03, 0.0, 0.0, 0.0])
    # the readings by the closure solve that the registration runs (`core.predicted`: `forward_with_status`, checked
    # against the Delta's direct solution to 1e-9 in tests/test_delta_builder.py), not a compile of the differentiable
    # closed forward (`core.readings`) for these 16 samples alone
    y = core.predicted(delta, dev, np.concatenate([delta.nominal_np, frame]), np.asarray(q, float))
    problem = core.make_problem(delta, dev, q, y, weights=np.ones(3), free=np.concatenate([delta.free_mask, dev.free_mask]),
                                a_ref=np.concatenate([delta.nominal_np, dev.nominal_np]))
    x = core.registered_frame(problem, problem.a_ref)
    nr = delta.n_params
    assert np.max(np.abs(x[nr:nr + 6] - frame[:6])) < 1e-9
    assert np.array_equal(x[:nr], delta.nominal_np) and not np.any(x[nr + 6:])


@pytest.mark.parametrize("kind", ["position", "pose"])
def test_identify_reaches_the_noise_floor_with_a_far_rotated_frame(stanford, kind):
    """Device frame 4 m away, rotated 150 degrees: identify ends at the noise floor on held-out samples (3-D RMS of
    0.05 mm per axis noise = 0.087 mm; bound 0.11 mm) and converges; the start was the registered frame."""
    rb, a_true = stanford
    data = simulated(rb, a_true, kind, 200, seed=2)
    train, test = data.split(0.75, seed=0)
    fit = jc.identify(rb, train, sigma_position=NOISE, sigma_orientation=NOISE)
    assert fit.converged and fit.info["registered_start"]
    held = fit.rms_on(test)
    assert held < 0.11, f"held-out {held:.4f} mm"
    assert fit.rms_before > 1.0  # the nominal geometry is millimetres off: the floor is the calibration's doing


def test_identify_reads_millimetres_and_refuses_them_unlabelled(stanford, tmp_path):
    """The same far-frame pose data written in mm with a units line calibrate to the same floor; the readings
    in mm given as metres are refused with an error that names the unit."""
    rb, a_true = stanford
    data = simulated(rb, a_true, "pose", 200, seed=3)
    path = tmp_path / "poses_mm.csv"
    data.to_csv(path, length_unit="mm", joints=rb.joint_names)
    mm = jc.Dataset.from_csv(path, joints=rb.joint_names, device="pose")
    train, test = mm.split(0.75, seed=0)
    fit = jc.identify(rb, train, sigma_position=NOISE, sigma_orientation=NOISE)
    assert fit.converged and fit.rms_on(test) < 0.11
    y_mm = data.y.copy()
    y_mm[:, :3, 3] *= 1e3
    with pytest.raises(DataError, match="mm"):
        jc.identify(rb, jc.Dataset(q=data.q, y=y_mm, device="pose"))


def test_gap_baseline_equals_identify_on_each_fold(stanford):
    """A fold is a sample-weight mask: the baseline of every fold is identify on that fold's samples (same
    estimate to 1e-7 of a typical size, same RMS to 1e-9 relative)."""
    rb, a_true = stanford
    data = simulated(rb, a_true, "position", 120, seed=4)
    masks = [np.arange(len(data)) % 3 != b for b in range(2)]
    cals = baseline_fits(rb, data, masks, sigma_position=1e-3, sigma_orientation=1e-3, max_steps=200)
    for mask, cal in zip(masks, cals):
        sub = data.subset(np.flatnonzero(mask))
        fit = jc.identify(rb, sub)
        assert tuple(np.flatnonzero(np.isin(fit.names, fit.estimated))) == tuple(cal.estimated)
        assert np.max(np.abs(np.asarray(fit.a_full) - cal.x) / core.x_scale(cal.problem.units)) < 1e-7
        rms_fold = jc.identify(rb, sub, a0=cal.x[:rb.n_params], device_params=cal.x[rb.n_params:], free=(),
                               known=("dev", "tool")).rms_before
        assert abs(rms_fold - fit.rms_after) <= 1e-9 * fit.rms_after


def test_a_robot_that_frees_few_entries_steps_on_their_columns_alone(stanford, monkeypatch):
    """Far frame, a robot that frees 12 of its 43 parameters (21 of 52 entries with the device's): `Problem.step_width`
    is 24, so every solve factors 24 columns (`lm.step_columns`), not 52 with 31 zeroed, the frames-only fit of
    `free=()` in the same program. The fit is the one of the arm that frees all 43 (every column, the held ones
    masked) told to estimate the same 12: same estimate to 1e-9 of a typical size, same RMS to 1e-9 relative,
    iterations within one (the last, at round-off). The errors are on those 12 alone: the fits reach the noise, as a
    model that holds the others right would (with the other 31 wrong, the health check's 22 frames-only fits for
    swapped joint columns ran too, 10 of this test's 15 s at the tests' LLVM level 0)."""
    rb, a_true = stanford
    few = rb.with_free(rb.names[:12])
    a_few = np.where(few.free_mask, np.asarray(a_true), rb.nominal_np)
    train, _ = simulated(rb, a_few, "position", 200, seed=2).split(0.75, seed=0)
    widths = []
    spied = core.compiled_model_solver
    monkeypatch.setattr(core, "compiled_model_solver", lambda *a, **k: widths.append(k.get("width")) or spied(*a, **k))
    narrow = jc.identify(few, train, sigma_position=NOISE)
    assert jc.identify(few, train, free=(), sigma_position=NOISE).converged
    assert set(widths) == {24}
    widths.clear()
    wide = jc.identify(rb, train, free=few.names[:12], sigma_position=NOISE)
    assert set(widths) == {None}
    assert narrow.converged and wide.converged and abs(narrow.iterations - wide.iterations) <= 1
    assert narrow.estimated == wide.estimated and set(few.names[:12]) & set(narrow.estimated)  # robot entries moved
    scale = core.x_scale(tuple(rb.units) + tuple(train.device.units))
    assert np.max(np.abs(np.asarray(narrow.a_full) - np.asarray(wide.a_full)) / scale) < 1e-9
    assert abs(narrow.rms_after - wide.rms_after) <= 1e-9 * wide.rms_after


def test_a_step_width_is_used_only_where_it_holds_every_estimated_entry(stanford):
    """`Problem.width_for`: the width of a robot that frees 12 entries (24 with the device's 9), for a mask of those
    21 (or a batch of such masks); None for a mask that estimates more than the width (a caller freeing entries the
    robot holds by default), so that no estimated entry is left out of the steps; None for a robot that frees most."""
    rb, a_true = stanford
    data = simulated(rb, a_true, "position", 12, seed=3)
    P = rb.n_params + data.device.n_params
    free = np.zeros(P, bool)
    free[:12] = free[rb.n_params:] = True
    problem = core.make_problem(rb.with_free(rb.names[:12]), data.device, data.q, data.y, weights=np.ones(3), free=free,
                                a_ref=np.zeros(P))
    assert problem.step_width == 24
    assert problem.width_for(free) == 24 and problem.width_for(np.stack([free, free])) == 24
    assert problem.width_for(np.ones(P)) is None
    wide = core.make_problem(rb, data.device, data.q, data.y, weights=np.ones(3), free=free, a_ref=np.zeros(P))
    assert wide.step_width is None


def test_unknown_solver_name_and_solver_objects():
    """One name -> solver map; an optimistix solver object is accepted as it is."""
    import optimistix as optx

    with pytest.raises(ValueError, match="unknown solver"):
        core.make_solver("levenberg", 1e-8, 1e-10)
    lm = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-11)
    assert core.make_solver(lm, 1.0, 1.0) is lm


@pytest.mark.parametrize("kind", ["position", pytest.param("pose", marks=pytest.mark.slow)])
def test_diagnose_finds_no_gap_with_a_far_rotated_frame(stanford, kind, tmp_path):
    """Clean data (no effect) through a device frame 4 m away and rotated 150 degrees, pose data read from a CSV
    in mm: the diagnosis baseline reaches the noise floor (held-out 3-D RMS below 0.11 mm for 0.05 mm per axis)
    and the verdict is "none" (it was "unexplained" at ~100 mm when the baseline had no registered start)."""
    rb, a_true = stanford
    data = simulated(rb, a_true, kind, 150, seed=5)
    if kind == "pose":
        path = tmp_path / "poses_mm.csv"
        data.to_csv(path, length_unit="mm", joints=rb.joint_names)
        data = jc.Dataset.from_csv(path, joints=rb.joint_names, device="pose")
    d = jc.gap.diagnose(rb, data)
    assert d.heldout_rms_before < 0.11, d.report()
    assert d.verdict == "none", d.report()


def _ur10_case(a_true_errors: float, seed: int = 3):
    """UR10 URDF chain, 40 positions with 0.02 mm noise, tracker 1.8 m away and turned 0.6 rad."""
    rb = jc.robots.get("ur10")
    a_true = jc.perturb(rb, a_true_errors, seed=seed) if a_true_errors else rb.nominal_np
    dev = jc.measure.devices.as_device("position")
    d = np.array(dev.nominal_np, float)
    d[:6] = [1.5, -0.8, 0.4, 0.2, -0.3, 0.5]
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 40, seed=4), "position", noise=2e-5, device_params=d, seed=5)
    q_new = jc.random_configurations(rb, 200, seed=9)
    y_new = jc.simulate(rb, a_true, q_new, "position", device_params=d).y
    return rb, dev, data, q_new, y_new


def _true_error_mm(fit, q_new, y_new) -> float:
    return float(np.sqrt(np.mean(np.sum((fit.predict(q_new) - y_new) ** 2, axis=1))) * 1e3)


def test_device_first_base_set_fits_urdf_joints_without_the_final_stage():
    """Issue 15 item 3 / 21 item 2: URDF joints (6 parameters each) with 1 mm / 1 mrad errors, tracker 1.8 m away.
    With the robot's base preferred to the tracker frame (before), the base set held the frame at the start's fit
    and the fit stopped 7x above the noise until the final stage freed it (0.18 -> 0.014 mm). With the device's
    parameters first, the base set estimates the frame and holds the robot's redundant base link at nominal: the
    base-set fit alone is at the noise (~0.014 mm), the final stage is not needed, and no robot entry moves more
    than a calibration correction."""
    rb, dev, data, q_new, y_new = _ur10_case(1e-3)
    fit = jc.identify(rb, data, sigma_position=2e-5)
    assert not fit.info["polish"]["tried"] and fit.converged and fit.health.ok
    assert _true_error_mm(fit, q_new, y_new) < 0.03
    assert {f"dev.{c}" for c in ("x", "y", "z", "rx", "ry", "rz")} <= set(fit.estimated) and not fit.held_at_start
    assert "shoulder_pan_joint.z" in fit.undetermined and fit.status("dev.x") == "estimated"
    assert np.abs(np.asarray(fit.a) - rb.nominal_np).max() < 0.01


def test_final_all_parameter_stage_frees_parameters_the_base_set_held():
    """The final stage (`core.polish`) on a fit that held parameters which matter at the solution (here: the
    elbow's and wrist 1's x, y and z, identifiable but held at nominal, as a base set chosen at a degenerate start
    would): one Gauss-Newton step predicts F >> POLISH_F, the stage is solved and kept, and the model predicts new
    poses at the noise (held: > 0.1 mm; freed: < 0.03 mm)."""
    rb, dev, data, q_new, y_new = _ur10_case(1e-3)
    free = np.concatenate([rb.free_mask, dev.free_mask])
    problem = core.make_problem(rb, dev, data.q, data.y, weights=dev.weights(2e-5, 1e-3), free=free,
                                a_ref=np.concatenate([rb.nominal_np, dev.nominal_np]))
    full = core.calibrate(problem, core.Settings(), final_polish=False)
    dropped = np.array([problem.names.index(f"{j}.{c}") for j in ("elbow_joint", "wrist_1_joint") for c in "xyz"])
    held_est = np.setdiff1d(full.estimated, dropped)
    assert held_est.size == full.estimated.size - np.intersect1d(full.estimated, dropped).size > 0
    held = core.solve(problem, full.x_frames, held_est, core.Settings())
    undetermined = np.union1d(full.undetermined, np.setdiff1d(full.estimated, held_est))

    def error_mm(x):
        y = jc.simulate(rb, x[: rb.n_params], q_new, "position", device_params=x[rb.n_params:]).y
        return float(np.sqrt(np.mean(np.sum((y - y_new) ** 2, axis=1))) * 1e3)

    assert error_mm(held.x) > 0.1
    sol, record = core.polish(problem, held.x, problem.jacobian(held.x), held_est, undetermined, core.Settings())
    assert record["tried"] and record["accepted"] and record["predicted_f_ratio"] > core.POLISH_F
    assert record["f_ratio"] > 10 * core.POLISH_F and sol.converged
    assert error_mm(sol.x) < 0.03


def test_a_calibration_from_an_earlier_start_counts_that_calibrations_times():
    """`identify`'s bias rule calibrates again from the unbiased calibration's start (`started`): the result's
    compile_s and run_s, which identify reports, include the earlier calibration's (they were only the second
    call's: on the Delta, compile 0.00 s and run 26 ms for a 10.5 s first call)."""
    rb, dev, data, _, _ = _ur10_case(1e-3)
    problem = core.make_problem(rb, dev, data.q, data.y, weights=dev.weights(2e-5, 1e-3),
                                free=np.concatenate([rb.free_mask, dev.free_mask]),
                                a_ref=np.concatenate([rb.nominal_np, dev.nominal_np]))
    first = dataclasses.replace(core.calibrate(problem, core.Settings()), compile_s=100.0, run_s=50.0)
    t = time.perf_counter()
    again = core.calibrate(problem, core.Settings(), bias=[1e-2, 0.0], started=first)
    wall = time.perf_counter() - t
    assert 100.0 <= again.compile_s and 50.0 < again.run_s and again.compile_s + again.run_s <= 150.0 + wall


def test_final_stage_is_not_kept_when_the_base_set_already_fits():
    """Same set-up with the nominal robot as the truth: the held parameters can only fit noise (F ~ 1), which one
    Gauss-Newton step predicts, so the stage is not even solved."""
    rb, dev, data, q_new, y_new = _ur10_case(0.0)
    fit = jc.identify(rb, data, sigma_position=2e-5)
    p = fit.info["polish"]
    assert not p["tried"] and p["predicted_f_ratio"] < core.POLISH_F
    assert not fit.polished and "undetermined (kept at prior)" in fit.report()
    assert _true_error_mm(fit, q_new, y_new) < 0.03


# ---- issue 21 item 2: a probe whose orientation barely moves ----------------------------------------------------

def _wrist_for_orientations(rb, a, q, targets):
    """q with the wrist joints (the last three) solved so that the tool orientation equals each target: damped
    Gauss-Newton on R(q) - R_target, vmapped over the samples."""
    import jax
    import jax.numpy as jnp

    def error(w, arm, Rt):
        return (jc.forward(rb, a, jnp.concatenate([arm, w])).R - Rt).reshape(-1)

    err, jac = jax.jit(jax.vmap(error)), jax.jit(jax.vmap(jax.jacfwd(error)))
    arm, w, T = jnp.asarray(q[:, :3]), jnp.asarray(q[:, 3:]), jnp.asarray(targets)
    for _ in range(100):
        J, e = jac(w, arm, T), err(w, arm, T)
        JtJ = jnp.swapaxes(J, 1, 2) @ J + 1e-3 * jnp.eye(3)
        w = w - jnp.linalg.solve(JtJ, jnp.swapaxes(J, 1, 2) @ e[..., None])[..., 0]
    assert float(jnp.abs(err(w, arm, T)).max()) < 1e-10
    return np.concatenate([q[:, :3], np.asarray(w)], axis=1)


def _estimated(fit) -> list[int]:
    return [fit.names.index(n) for n in fit.std_errors]


def _regrouped_truth(fit, truth) -> np.ndarray:
    """The truth written in the fit's base set (seed 001 eq 37): each estimated entry absorbs beta (truth - held value)
    of the entries held, beta from the Jacobian at the solution. Only this, not the raw truth, is what the estimate
    and its standard error describe when some parameters are regrouped."""
    J, est = np.asarray(fit.jacobian), np.asarray(fit.a_full)
    e = _estimated(fit)
    held = [i for i in range(len(fit.names)) if i not in e]
    beta = np.linalg.lstsq(J[:, e], J[:, held], rcond=None)[0]
    return truth[e] + beta @ (truth[held] - est[held])


def test_a_probe_that_barely_turns_gives_sane_values_and_honest_errors(stanford):
    """A pose probe whose orientation turns by <= 0.1 degree over 200 poses, tracker 3 m away: the tool offset and
    the tracker position can then only be told apart to ~cm. Before, a real case of this shape returned a tracker
    frame 458 m away with 3 um standard errors; here the fit converges, predicts new poses of the same kind at the
    noise, keeps the frame within 5 cm and the robot within calibration-sized corrections (with the robot's base
    preferred to the tracker frame: frame 0.16 m off, on 2500 poses the base height 0.52 m), every standard error
    covers its parameter's error against the truth written in the fit's base set (before this check the base-set
    block gave j1.d 2.5 mm for a 0.19 m error, z = 75); the report names the poorly determined parameters."""
    from scipy.spatial.transform import Rotation

    rb, a_true = stanford
    rng = np.random.default_rng(0)
    q = np.asarray(jc.random_configurations(rb, 260, seed=2))
    R0 = np.asarray(jc.forward(rb, a_true, q[0]).R)
    turns = Rotation.from_rotvec(rng.normal(size=(260, 3)) * np.deg2rad(0.05) / np.sqrt(3)).as_matrix()
    q = _wrist_for_orientations(rb, a_true, q, R0 @ turns)
    d = np.zeros(12)
    d[:6] = [2.5, -1.2, 0.8, 0.3, -0.2, 2.0]
    noise = {"position": 3e-5, "orientation": 1e-5}
    data = jc.simulate(rb, a_true, q[:200], "pose", noise=noise, device_params=d, seed=5)
    new = jc.simulate(rb, a_true, q[200:], "pose", device_params=d)
    fit = jc.identify(rb, data, sigma_position=3e-5, sigma_orientation=1e-5)
    assert fit.converged and fit.health.residual_ratio < 1.2
    held_out = np.sqrt(np.mean(np.sum((fit.predict(new.q)[:, :3] - new.y[:, :3]) ** 2, axis=1)))
    assert held_out < 1e-4, held_out
    assert np.linalg.norm(np.asarray(fit.device_params[:3]) - d[:3]) < 0.05  # measured 0.015 m (robot first: 0.16 m)
    truth = np.concatenate([np.asarray(a_true), d])
    est = np.asarray(fit.a_full)
    se = np.array(list(fit.std_errors.values()))
    z = dict(zip(fit.std_errors, np.abs(est[_estimated(fit)] - _regrouped_truth(fit, truth)) / se))
    assert max(z.values()) < 4.0, sorted(z.items(), key=lambda t: -t[1])[:3]
    assert not fit.health.implausible  # no robot entry beyond a calibration correction (measured: 19 mm at most)
    weak = fit.poorly_determined()
    assert {"tool.x", "tool.y", "tool.z", "dev.x"} <= set(weak) and "poorly determined" in fit.report()


@pytest.mark.parametrize("name", ["stanford", "fourbar2d"])
def test_jacobian_from_the_solver_program_is_jacfwd_and_predicted_is_readings(name):
    """`Problem.jacobian` (the solver's executable run for 0 iterations) equals jax.jacfwd of the weighted residuals
    (float64, relative 1e-12; measured 5.2e-16 on the Stanford arm, 0 on the four-bar), the run leaves the point
    where it is, and `core.predicted` (a closed mechanism: one closure solve, then the open tree) equals the
    differentiable `core.readings` to 1e-12 m, also for other arrays of the same shapes (its results are kept by
    content). A solve of a third of the entries returns the Jacobian of every
    column at its end (`Solution.J`, which `calibrate` uses instead of running the program again): equal to
    `Problem.jacobian` there (relative 1e-12). With the robot held, the program's cheaper device-only Jacobian
    (`RobotDevice.residual_and_jacobian` with robot_held) gives the same device columns, residual and fitted frame."""
    import jax

    rb = jc.robots.get(name)
    dev = jc.make_device("position")
    a = np.concatenate([np.asarray(jc.perturb(rb, 1e-3, seed=2)), far_frame(dev)])
    q = jc.random_configurations(rb, 12, seed=3)
    y = np.asarray(core.readings(rb, dev, a, q)) + 1e-4 * np.sin(np.arange(36.0)).reshape(12, 3)  # a non-zero residual
    np.testing.assert_allclose(core.predicted(rb, dev, a, q), core.readings(rb, dev, a, q), rtol=0, atol=1e-12)
    # the readings kept by content (`core.predicted`): new arrays of other values are evaluated, not served stale
    q_moved, a_moved = q.copy(), a.copy()
    q_moved[5, 0] += 0.1
    a_moved[0] += 1e-3
    for a_i, q_i in ((a, q_moved), (a_moved, q)):
        kept = core.predicted(rb, dev, a_i, q_i)
        np.testing.assert_allclose(kept, core.readings(rb, dev, a_i, q_i), rtol=0, atol=1e-12)
        assert not kept.flags.writeable
    assert not np.allclose(core.predicted(rb, dev, a, q_moved)[5], core.predicted(rb, dev, a, q)[5])
    w = np.full((12, 3), 1e3)
    problem = core.Problem(rb, dev, q, y, w, np.ones(len(a), bool), a, np.full(len(a), -np.inf), np.full(len(a), np.inf))
    J = problem.jacobian(a)
    J_fwd = np.asarray(jax.jacfwd(lambda v: core.residuals(rb, dev, v, q, y, w).reshape(-1))(a))
    err = np.max(np.abs(J - J_fwd)) / np.max(np.abs(J_fwd))
    assert err < 1e-12, err
    args = problem.solver_arrays(a, np.ones(len(a)), w, 0.0, np.ones(len(a)))
    exe, _ = core.evaluator(problem, args)
    x, _, steps, *_ = exe(a, args, core.step_limit(0))
    assert int(steps) == 0 and np.array_equal(np.asarray(x), a)
    sol = core.solve(problem, a, np.arange(0, len(a), 3), core.Settings())
    assert sol.steps > 0 and not np.array_equal(sol.x, a)
    J_end = problem.jacobian(sol.x)
    err = np.max(np.abs(sol.J - J_end)) / np.max(np.abs(J_end))
    assert err < 1e-12, err
    # the robot held (no robot entry estimated): the same program reads the device columns off the given tool poses
    # (`RobotDevice.residual_and_jacobian` with robot_held), equal to jacfwd's (measured 5.2e-16 / 4.4e-16), the robot's 0, and the
    # residual r the same as with the kinematics differentiated
    dev_cols = np.arange(rb.n_params, len(a))
    J_held = problem.jacobian(a, dev_cols)
    err = np.max(np.abs(J_held[:, dev_cols] - J_fwd[:, dev_cols])) / np.max(np.abs(J_fwd[:, dev_cols]))
    assert err < 1e-12, err
    assert not np.any(J_held[:, :rb.n_params])
    held_args = problem.solver_arrays(a, np.isin(np.arange(len(a)), dev_cols).astype(float), w, 0.0, np.ones(len(a)))
    r_held, r_full = exe(a, held_args, core.step_limit(0))[5], exe(a, args, core.step_limit(0))[5]
    np.testing.assert_allclose(r_held, r_full, rtol=0, atol=1e-12 * np.max(np.abs(r_full)))
    # a fit of device entries alone returns no Jacobian (its robot columns are 0) unless asked for every column (below),
    # and reaches the optimum that optimistix's LM (the kinematics differentiated) reaches (measured 1.6e-11 / 5.1e-13)
    start = a.copy()
    start[dev_cols[:3]] += 0.02
    mine = core.solve(problem, start, dev_cols, core.Settings())
    theirs = core.solve(problem, start, dev_cols, core.Settings("lm_optimistix", rtol=1e-10, atol=1e-12))
    assert mine.J is None and mine.converged and theirs.converged
    np.testing.assert_allclose(mine.x, theirs.x, rtol=0, atol=1e-8)
    # asked for every column (`solve`'s full: the start of `calibrate`, whose next fit and base set take them), the same
    # fit returns J at its end with the robot's columns, equal to `Problem.jacobian` there, and the triangular factor of
    # [J r] (`triangular`: R^T R equal to [J r]^T [J r]), from a start that has every column too; the same estimate as
    # without (measured, Stanford arm / four-bar: J 2.7e-16 / 3.1e-16 relative, R^T R 3.2e-16 / 4.3e-16, x 0 / 1.0e-14)
    full = core.solve(problem, start, dev_cols, core.Settings(), start=problem.residual_and_jacobian(start), factor=True,
                      full=True)
    np.testing.assert_allclose(full.x, mine.x, rtol=0, atol=1e-12)
    J_end = problem.jacobian(full.x)
    assert np.any(full.J[:, :rb.n_params]) and rel_err(full.J, J_end) < 1e-12
    A = np.concatenate([J_end, full.r.reshape(-1, 1)], axis=1)
    assert rel_err(full.factor.T @ full.factor, A.T @ A) < 1e-12


@pytest.mark.parametrize("name", ["stanford", "fourbar2d"])
def test_a_solve_given_its_start_is_the_solve_that_evaluates_it(name):
    """`core.solve` given start = (r, J) at x0 skips the solver's first evaluation and is otherwise the same run: the
    same steps, estimate (1e-10 absolute: the solver stops at 1e-8 typical sizes of 1 cm or 0.01 rad, and the start
    differs from the evaluated one by round-off; measured 7e-12) and cost (relative 1e-9), for a bias stage from
    where the last stage ended (x0 is not the prior ref: `Solution.read`), a fit of device entries alone (the robot's
    columns 0: `Problem.residual_and_jacobian` with those columns) and a fold (`core.reweighted` from the whole
    problem's). The read's r is `Problem.residuals`; a fold cannot take the start of a problem that left out a sample
    it weights, and a start off the prior on the entries the solve holds is refused."""
    rb = jc.robots.get(name)
    dev = jc.make_device("position")
    a = np.concatenate([np.asarray(jc.perturb(rb, 1e-3, seed=2)), far_frame(dev)])
    q = jc.random_configurations(rb, 12, seed=3)
    y = np.asarray(core.readings(rb, dev, a, q)) + 1e-4 * np.sin(np.arange(36.0)).reshape(12, 3)
    w = np.full((12, 3), 1e3)
    problem = core.Problem(rb, dev, q, y, w, np.ones(len(a), bool), a, np.full(len(a), -np.inf), np.full(len(a), np.inf))
    settings = core.Settings()

    def same_run(given, evaluated):
        assert given.steps == evaluated.steps > 0 and given.converged == evaluated.converged
        np.testing.assert_allclose(given.x, evaluated.x, rtol=0, atol=1e-10)
        assert abs(given.cost - evaluated.cost) <= 1e-9 * evaluated.cost

    r, J = problem.residual_and_jacobian(a)
    np.testing.assert_allclose(r, problem.residuals(a), rtol=0, atol=1e-12 * np.max(w))  # 1e-12 m of a reading
    est = np.arange(0, len(a), 3)
    first = core.solve(problem, a, est, settings, start=(r, J))
    same_run(first, core.solve(problem, a, est, settings))
    same_run(core.solve(problem, first.x, est, settings, mu=1e-2, ref=a, start=first.read),
             core.solve(problem, first.x, est, settings, mu=1e-2, ref=a))
    dev_cols = np.arange(rb.n_params, len(a))
    moved = a.copy()
    moved[dev_cols[:3]] += 0.02
    held = problem.residual_and_jacobian(moved, dev_cols)
    same_run(core.solve(problem, moved, dev_cols, settings, start=held), core.solve(problem, moved, dev_cols, settings))
    fold_w = w.copy()
    fold_w[::4] = 0.0
    fold = problem.with_weights(fold_w)
    same_run(core.solve(fold, a, est, settings, start=core.reweighted((r, J), w, fold_w)), core.solve(fold, a, est, settings))
    assert core.reweighted((r, J), fold_w, w) is None
    with pytest.raises(ValueError, match="entries not estimated"):
        core.solve(problem, first.x + 1e-3, est, settings, ref=a, start=first.read)


def test_a_fit_ends_within_its_relative_offset_of_the_optimum(stanford, monkeypatch):
    """`core.OFFSET_TOL` (Bates and Watts' relative offset): the calibration's fits end, converged, at a step predicted
    to lower the cost by at most OFFSET_TOL^2 p s^2, that step not evaluated. On 150 noisy poses seen from a far
    rotated frame the main fit ends one evaluation earlier than without the stop (its last step not taken), at a point
    whose distance from the optimum that the fit without it reached, |J (x - x_opt)| in weighted readings, is within
    OFFSET_TOL of the confidence region's radius sqrt(p) s (measured 2e-5 of it). Noise-free readings (s^2 at
    round-off) run as without it: the same steps and estimate to the bit."""
    rb, a_true = stanford
    dev = jc.make_device("pose")
    noisy = simulated(rb, a_true, "pose", 200, seed=2).split(0.75, seed=0)[0]
    q = np.asarray(noisy.q)
    exact = np.asarray(core.readings(rb, dev, np.concatenate([np.asarray(a_true), far_frame(dev)]), q))
    a_ref = np.concatenate([rb.nominal_np, dev.nominal_np])
    free = np.concatenate([rb.free_mask, dev.free_mask])

    def calibrations(y):
        problem = core.make_problem(rb, dev, q, y, weights=np.full(6, 1.0 / NOISE), free=free, a_ref=a_ref)
        out = {}
        for tol in (0.0, core.OFFSET_TOL):
            monkeypatch.setattr(core, "OFFSET_TOL", tol)
            out[tol] = core.calibrate(problem)
        return out[0.0], out[core.OFFSET_TOL]

    full, stopped = calibrations(np.asarray(noisy.y))
    assert full.converged and stopped.converged and stopped.iterations == full.iterations
    assert stopped.history[-1] == stopped.history[-2] and full.history[-1] < full.history[-2]  # the last step not taken
    est = full.estimated
    np.testing.assert_array_equal(stopped.estimated, est)
    readings, p = int(np.sum(full.problem.w != 0)), len(est)
    s = np.sqrt(np.sum(full.residuals**2) / (readings - p))
    offset = np.linalg.norm(full.J[:, est] @ (stopped.x - full.x)[est])
    assert 0.0 < offset <= core.OFFSET_TOL * np.sqrt(p) * s, (offset, np.sqrt(p) * s)
    full, stopped = calibrations(exact)
    assert stopped.iterations == full.iterations and np.array_equal(stopped.x, full.x)


def test_the_solver_program_returns_the_factor_of_its_jacobian_and_residual(stanford):
    """`core.data_factor`: the triangular factor T of the data rows' [J r] that a read (`Problem.read`) and a solve
    asked for it return, computed in the solver's program, is the host's (`core.triangular`): T^T T = [J r]^T [J r]
    to 1e-12 of its largest entry, after a solve in z with scaled weights too (`solver_residual_and_jacobian`); a
    solve not asked returns none. The calibration's base set from the read's factor (P + 1 rows) is the one from J
    (N m rows), and its final stage's factor is the host's of [J r] at the solution."""
    rb, a_true = stanford
    dev = jc.make_device("pose")
    data = simulated(rb, a_true, "pose", 120, seed=5)
    free = np.concatenate([rb.free_mask, dev.free_mask])
    problem = core.make_problem(rb, dev, data.q, data.y, weights=np.full(6, 1.0 / NOISE), free=free,
                                a_ref=np.concatenate([rb.nominal_np, dev.nominal_np]))

    def agrees(T, J, r):
        A = np.column_stack([J, np.reshape(r, -1)])
        assert T.shape == (A.shape[1], A.shape[1]) and np.allclose(np.tril(T, -1), 0.0)
        np.testing.assert_allclose(T.T @ T, A.T @ A, rtol=0, atol=1e-12 * np.max(np.abs(A.T @ A)))

    x = problem.a_ref.copy()
    x[rb.n_params:] = far_frame(dev)
    r, J, T = problem.read(x, factor=True)
    agrees(T, J, r)
    assert problem.read(x)[2] is None
    est = np.flatnonzero(free)[::2]
    sol = core.solve(problem, x, est, core.Settings(), limit=2, factor=True)
    agrees(sol.factor, sol.J, sol.r)
    assert core.solve(problem, x, est, core.Settings(), limit=2).factor is None
    for on_T, on_J in zip(core.choose_estimated(problem, J, True, None, T), core.choose_estimated(problem, J, True, None)):
        np.testing.assert_array_equal(on_T, on_J)
    cal = core.calibrate(problem)
    agrees(cal.factor0, cal.J0, cal.r0)
    assert cal.factor is not None  # the last stage's factor (its leading block J's), or the polish's
    np.testing.assert_allclose(cal.R.T @ cal.R, cal.J.T @ cal.J, rtol=0, atol=1e-12 * np.max(np.abs(cal.J.T @ cal.J)))


def test_the_triangular_factor_answers_for_the_jacobian_whatever_its_rank():
    """`core.triangular` (R = Q^T J): R^T R = J^T J, the singular values and right singular vectors of any columns are
    J's, and least squares on columns of [J r] has J's residual, also for a rank-deficient J (two columns equal, one
    zero); `core.linear_f_ratio` on it equals the F ratio of numpy's lstsq on J itself (relative 1e-10)."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(300, 12)) * np.logspace(0, -6, 12)
    J[:, 7], J[:, 9] = J[:, 2], 0.0
    r = rng.normal(size=300)
    R = core.triangular(J)
    assert R.shape == (12, 12) and np.allclose(np.tril(R, -1), 0.0)
    np.testing.assert_allclose(R.T @ R, J.T @ J, rtol=0, atol=1e-12 * np.max(np.abs(J.T @ J)))
    cols = np.array([0, 2, 5, 7, 11])
    np.testing.assert_allclose(np.linalg.svd(R[:, cols], compute_uv=False), np.linalg.svd(J[:, cols], compute_uv=False),
                               rtol=1e-10, atol=1e-14)
    T = core.triangular(np.column_stack([J, r]))
    resid = lambda A, b: np.sum((b - A @ np.linalg.lstsq(A, b, rcond=None)[0]) ** 2)  # noqa: E731
    assert abs(resid(T[:, cols], T[:, -1]) - resid(J[:, cols], r)) <= 1e-10 * resid(J[:, cols], r)
    est, added = np.array([0, 1, 2, 3]), np.array([5, 7, 9])
    Jc = J[:, np.concatenate([est, added])]
    Jc = Jc / np.maximum(np.linalg.norm(Jc, axis=0), 1e-300)
    direct = core.f_ratio(float(r @ r), resid(Jc, -r), len(added), 300 - 7)
    assert abs(core.linear_f_ratio(r, J, est, added, 300 - 7) - direct) <= 1e-10 * abs(direct)


def test_solver_compile_options_are_used_on_cpu_and_left_out_where_unknown(monkeypatch):
    """`compile_solver` compiles with CPU_COMPILE_OPTIONS on the CPU backend; a jaxlib that does not know one of
    them gets the program compiled without (not an error); another compile error is not swallowed."""
    import jax
    import jax.numpy as jnp

    lowered = jax.jit(lambda x: 2.0 * x + 1.0).lower(jnp.arange(3.0))
    assert jax.default_backend() == "cpu"
    np.testing.assert_array_equal(core.compile_solver(lowered, False)(jnp.arange(3.0)), [1.0, 3.0, 5.0])
    monkeypatch.setattr(core, "CPU_COMPILE_OPTIONS", {"xla_cpu_no_such_option_of_jaxcal": False})
    np.testing.assert_array_equal(core.compile_solver(lowered, False)(jnp.arange(3.0)), [1.0, 3.0, 5.0])
    with pytest.raises(Exception, match="No such compile option"):
        lowered.compile(compiler_options=core.CPU_COMPILE_OPTIONS)  # what the fallback answers
    monkeypatch.setattr(core, "CPU_COMPILE_OPTIONS", {"xla_cpu_use_fusion_emitters": "not a flag value"})
    with pytest.raises(Exception):
        core.compile_solver(lowered, False)


def test_solvers_of_open_chains_and_the_delta_compile_without_ynnpack_other_closed_mechanisms_with(monkeypatch):
    """An open chain's solver, and the Delta's, leave XLA:CPU's dots to XLA (XLA_DOTS_CPU_OPTIONS: no `__ynn_fusion`
    library calls); the other closed mechanisms keep jaxlib's default (`core.xla_dots`); a jaxlib that does not know
    the option compiles with the others."""
    import jax
    import jax.numpy as jnp

    lowered = jax.jit(lambda a, b: jnp.tanh(a @ b)).lower(jnp.ones((64, 64)), jnp.ones((64, 64)))
    default_uses_ynn = "__ynn_fusion" in lowered.compile().as_text()
    assert "__ynn_fusion" not in core.compile_solver(lowered, False, own_dots=True).as_text()
    assert ("__ynn_fusion" in core.compile_solver(lowered, False, own_dots=False).as_text()) == default_uses_ynn
    monkeypatch.setattr(core, "XLA_DOTS_CPU_OPTIONS", {"xla_cpu_no_such_option_of_jaxcal": ""})
    np.testing.assert_allclose(core.compile_solver(lowered, False, own_dots=True)(jnp.eye(64), jnp.eye(64)),
                               np.tanh(np.eye(64)))
    position = jc.measure.devices.as_device("position")
    own = {name: core.xla_dots(core.RobotDevice(jc.robots.get(name), position)) for name in ("stanford", "delta", "fourbar2d")}
    assert own == {"stanford": True, "delta": True, "fourbar2d": False}, own
