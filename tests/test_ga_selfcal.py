"""Self-calibration with a pointing tool and two targets at a known distance (seed 000 §7.4)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.ga import selfcal as sc


@pytest.fixture(scope="module")
def stanford_aims():
    """Stanford arm (43 parameters); the truth differs from nominal by up to 1 mm / mrad in the
    parameters this method can identify; 30 aims per target found by IK under the truth."""
    rb = jc.robots.get("stanford")
    q0 = jnp.asarray(rb.home)
    q0b = q0 + jnp.asarray(np.random.default_rng(0).uniform(-0.3, 0.3, rb.n_inputs))
    rng = np.random.default_rng(1)
    s1, s2 = q0 + rng.uniform(-0.4, 0.4, (30, 6)), q0b + rng.uniform(-0.4, 0.4, (30, 6))
    free = np.flatnonzero(rb.free_mask)
    tn, tb = jc.forward(rb, rb.nominal, q0), jc.forward(rb, rb.nominal, q0b)
    t1, t2 = tn.p + 0.3 * tn.R[:, 2], tb.p + 0.3 * tb.R[:, 2]
    Q1n, _ = sc.aim_configurations(rb, rb.nominal, t1, s1)
    Q2n, _ = sc.aim_configurations(rb, rb.nominal, t2, s2)
    det = sc.identifiable(rb, rb.nominal, Q1n, Q2n, float(jnp.linalg.norm(t1 - t2)), free)
    est = np.sort(det.estimated)
    a_true = np.asarray(rb.nominal_np).copy()
    a_true[est] += rng.uniform(-1e-3, 1e-3, len(est))
    Q1, r1 = sc.aim_configurations(rb, jnp.asarray(a_true), t1, s1)
    Q2, r2 = sc.aim_configurations(rb, jnp.asarray(a_true), t2, s2)
    assert float(jnp.max(r1)) < 1e-12 and float(jnp.max(r2)) < 1e-12
    return rb, a_true, Q1, Q2, float(jnp.linalg.norm(t1 - t2)), est, det


def test_identifiable_set_of_pointing_self_calibration(stanford_aims):
    """Jacobian rank 26 of 43 once the 6 target coordinates are taken out (measured: SVD rank 32 of the
    43 + 6 free columns, QR base set 32 = 6 targets + 26 robot parameters, same threshold core.BASE_TOL):
    the 6 gains are identifiable from joint readings alone (scale comes from the known distance d); the
    base frame terms j1.theta/j1.r and the others regroup (base-set tool, seed 001 App. III)."""
    rb, _, _, _, _, est, det = stanford_aims
    names = [rb.names[i] for i in est]
    assert det.robot_rank == len(est) == 26
    assert det.rank == det.base_count == 32 and len(det.device_estimated) == 6 and not det.problems
    assert {"j1.K", "j2.K", "j3.K", "j4.K", "j5.K", "j6.K"} <= set(names)


def test_lm_recovers_identifiable_parameters_from_joint_readings_only(stanford_aims):
    """Through the core (aim-line device, core.solve on the base set and the two targets)."""
    rb, a_true, Q1, Q2, d, est, _ = stanford_aims
    a, ok = sc.identify_lm(rb, Q1, Q2, d, est)
    assert ok
    err = np.abs(np.asarray(a) - a_true)[est]
    assert err.max() < 1e-8, dict(zip([rb.names[i] for i in est], err))
    assert float(jnp.max(jnp.abs(sc.residual(rb, jnp.asarray(a), Q1, Q2, d)))) < 1e-10


def test_selfcal_residual_jacobian_matches_central_differences(stanford_aims):
    """jacfwd through the closed-form target elimination vs central FD (h = 1e-6): rel. err < 1e-6."""
    import jax
    from conftest import central_fd, rel_err

    rb, a_true, Q1, Q2, d, _, _ = stanford_aims
    Q1s, Q2s = Q1[:5], Q2[:5]
    f = jax.jit(lambda a: sc.residual(rb, a, Q1s, Q2s, d))
    J = np.asarray(jax.jacfwd(f)(jnp.asarray(a_true)))
    assert rel_err(J, central_fd(f, a_true)) < 1e-6


def test_ga_reduces_the_self_calibration_residual(stanford_aims):
    """GA on the identifiable set with the same residual (sum of squares): measured cost falls by
    200 generations of 50 (26 variables, bound +-2 mm / mrad): 9.3e-6 at nominal -> 4.7e-8 (measured,
    factor 5e-3; the GA does not reach the LM optimum ~0 here, see docs/ga.md)."""
    rb, a_true, Q1, Q2, d, est, _ = stanford_aims
    a, best = sc.identify_ga(rb, Q1, Q2, d, est, population=50, generations=200, bound=0.002, seed=0)
    f0 = float(jnp.sum(sc.residual(rb, rb.nominal, Q1, Q2, d) ** 2))
    assert np.all(np.diff(best) <= 1e-18)
    assert best[-1] < 0.05 * f0, (best[-1], f0)


@pytest.fixture(scope="module")
def stanford_pose_targets():
    """Pose-target variant: 15 full-pose targets on a fixture (poses known relative to each other,
    the fixture's pose unknown); the truth differs from nominal by up to 1 mm / mrad in the
    parameters this method can identify; the joint readings come from IK under the truth."""
    rb = jc.robots.get("stanford")
    rng = np.random.default_rng(11)
    q_nominal = jnp.asarray(rb.home) + jnp.asarray(rng.uniform(-0.5, 0.5, (15, rb.n_inputs)))
    X = jc.forward(rb, rb.nominal, q_nominal)
    X = jnp.concatenate([jnp.concatenate([X.R, X.p[..., None]], -1),
                         jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (15, 1, 4))], -2)
    free = np.flatnonzero(rb.free_mask)
    det = sc.pose_target_identifiable(rb, rb.nominal, q_nominal, X, free)
    est = np.sort(det.estimated)
    a_true = np.asarray(rb.nominal_np).copy()
    a_true[est] += rng.uniform(-1e-3, 1e-3, len(est))
    Q, r = sc.pose_configurations(rb, jnp.asarray(a_true), X, q_nominal)
    assert float(jnp.max(r)) < 1e-12
    return rb, a_true, Q, X, est, det


def test_pose_target_identifiable_set(stanford_pose_targets):
    """Jacobian rank 28 of 43 (measured): relative poses cannot see the base frame; the 15 others
    are j0.theta, j0.r, all of frame 1 (alpha, d, theta, r, beta), j2.beta, j3.theta, j3.beta,
    j4.d, j4.r, j5.beta, j6.r, j6.beta (regrouped). The six gains are identifiable (joint readings
    against known relative poses)."""
    rb, _, _, _, est, det = stanford_pose_targets
    names = {rb.names[i] for i in est}
    assert det.robot_rank == len(est) == 28
    assert det.rank == det.base_count == 34 and len(det.device_estimated) == 6 and not det.problems
    assert {"j1.K", "j2.K", "j3.K", "j4.K", "j5.K", "j6.K"} <= names
    assert "j1.theta" not in names and "j1.r" not in names


def test_pose_target_lm_recovers_identifiable_parameters_from_joint_readings_only(stanford_pose_targets):
    """Through the core (pose-target device: fixture frame registered, then core.solve)."""
    rb, a_true, Q, X, est, _ = stanford_pose_targets
    a, ok = sc.identify_pose_target_lm(rb, Q, X, est)
    assert ok
    err = np.abs(np.asarray(a) - a_true)[est]
    assert err.max() < 1e-8, dict(zip([rb.names[i] for i in est], err))
    assert float(jnp.max(jnp.abs(sc.pose_target_residual(rb, jnp.asarray(a), Q, X)))) < 1e-10


def test_pose_target_residual_jacobian_matches_central_differences(stanford_pose_targets):
    """jacfwd of the pose-target residual vs central FD (h = 1e-6): rel. err < 1e-6."""
    import jax
    from conftest import central_fd, rel_err

    rb, a_true, Q, X, _, _ = stanford_pose_targets
    f = jax.jit(lambda a: sc.pose_target_residual(rb, a, Q[:5], X[:5]))
    assert rel_err(jax.jacfwd(f)(jnp.asarray(a_true)), central_fd(f, a_true)) < 1e-6


@pytest.mark.slow
def test_pose_target_ga_reduces_the_residual(stanford_pose_targets):
    """GA (50 x 200, bound +-2 mm / mrad) on the 28 identifiable parameters with the pose-target
    residual: the best cost falls below 5% of the nominal robot's (measured 3.7e-5 -> 3.0e-7, factor
    8e-3; like the two-target GA it does not reach the LM optimum ~0)."""
    rb, _, Q, X, est, _ = stanford_pose_targets
    a, best = sc.identify_pose_target_ga(rb, Q, X, est, population=50, generations=200, bound=0.002, seed=0)
    f0 = float(jnp.sum(sc.pose_target_residual(rb, rb.nominal, Q, X) ** 2))
    assert np.all(np.diff(best) <= 1e-18)
    assert best[-1] < 0.05 * f0, (best[-1], f0)


# -- the aim-line device and MRR-1 (issue 20 item 1) --------------------------------------------------------
def _mrr1_aims(direction, a_true=None, n=30):
    """MRR-1 aims at two targets 0.3 m along the pointer from two configurations; IK under a_true."""
    rb = jc.robots.get("mrr1")
    a = rb.nominal if a_true is None else jnp.asarray(a_true)
    q0 = jnp.asarray(rb.home)
    q0b = q0 + jnp.asarray([0.3, -0.4, 0.05])
    rng = np.random.default_rng(1)
    s1, s2 = q0 + rng.uniform(-0.4, 0.4, (n, 3)), q0b + rng.uniform(-0.4, 0.4, (n, 3))
    u = jnp.asarray(direction) / jnp.linalg.norm(jnp.asarray(direction))
    tn, tb = jc.forward(rb, rb.nominal, q0), jc.forward(rb, rb.nominal, q0b)
    t1, t2 = tn.p + 0.3 * tn.R @ u, tb.p + 0.3 * tb.R @ u
    Q1, r1 = sc.aim_configurations(rb, a, t1, s1, direction)
    Q2, r2 = sc.aim_configurations(rb, a, t2, s2, direction)
    assert float(jnp.max(r1)) < 1e-12 and float(jnp.max(r2)) < 1e-12
    return rb, Q1, Q2, float(jnp.linalg.norm(t1 - t2))


def test_mrr1_tool_z_pointer_is_refused():
    """MRR-1's tool z axis always points straight down: every aim line is vertical. Measured: QR base set 5
    (target1 x, y, z, target2 x, y) = SVD rank 5 under the same threshold; target2.z is dependent (only the
    difference of the heights enters |p1 - p2|) and no robot parameter is identifiable (robot rank 0; the
    old closed-form elimination solved a singular 3x3 system here: largest singular value 3.7e16, QR 3 vs
    numpy rank 1). The calibration refuses, or warns with strict=False."""
    rb, Q1, Q2, d = _mrr1_aims((0.0, 0.0, 1.0))
    det = sc.identifiable(rb, rb.nominal, Q1, Q2, d)
    assert det.rank == det.base_count == 5 and det.robot_rank == 0 and det.estimated.size == 0
    assert det.device_undetermined == ("target2.z",)
    with pytest.raises(sc.SelfCalibrationError, match="target2.z"):
        sc.calibrate(rb, [Q1, Q2], d)
    with pytest.warns(UserWarning, match="no robot parameter is identifiable"):
        sc.calibrate(rb, [Q1, Q2], d, strict=False)


@pytest.mark.slow  # 50 s here (IK, start, Jacobian and two solver compiles)
def test_mrr1_tilted_pointer_recovers_the_identifiable_parameters():
    """A pointer at 45 degrees to the tool z axis (direction (1, 0, 1) in the tool frame) sweeps its aim
    lines around each target: both targets are determined and, at the nominal MRR-1, 7 robot parameters are
    identifiable (measured: j1.bx, j1.by, j2.by, j2.pitch, j2.roll, j3.pitch, j3.roll; QR 13 = SVD rank 13).
    Errors of 1 mm / mrad in those 7, aims by IK under the truth: the core (core.solve on those 7 and the
    targets) recovers them to < 1e-8 (measured ~1e-12) and the targets to < 1e-8 m.
    At a generic robot (all 18 parameters off nominal) the rank is 16: the tilts j1.pitch, j1.roll, j1.yaw
    act only to second order at MRR-1's exactly parallel axes (singular values 1e-4 .. 3e-6 of 17.8,
    measured), so core.calibrate's own base set at its start (nominal robot, true aims) takes them too."""
    direction = (1.0, 0.0, 1.0)
    rb, Q1n, Q2n, d = _mrr1_aims(direction)
    det = sc.identifiable(rb, rb.nominal, Q1n, Q2n, d, direction=direction)
    assert det.rank == det.base_count == 13 and det.robot_rank == len(det.estimated) == 7 and not det.problems
    a_true = np.asarray(rb.nominal_np).copy()
    a_true[det.estimated] += np.random.default_rng(4).uniform(-1e-3, 1e-3, 7)
    _, Q1, Q2, _ = _mrr1_aims(direction, a_true)
    res = sc.calibrate(rb, [Q1, Q2], d, direction=direction, estimated=det.estimated)
    assert res.converged and res.solution is not None
    err = np.abs(res.a - a_true)[det.estimated]
    assert err.max() < 1e-8, dict(zip([rb.names[i] for i in det.estimated], err))
    u = np.array(direction) / np.sqrt(2.0)
    tn = jc.forward(rb, rb.nominal, jnp.asarray(rb.home))
    assert np.abs(res.device_params[:3] - np.asarray(tn.p + 0.3 * tn.R @ u)).max() < 1e-8
    full = sc.calibrate(rb, [Q1, Q2], d, direction=direction)  # core.calibrate: its own base set
    assert full.converged and full.determinacy.rank == full.determinacy.base_count == 16
    assert full.calibration.problem.cost(np.concatenate([full.a, full.device_params])) < 1e-20


@pytest.mark.parametrize("kind, options", [("aim_line", dict(targets=3, direction=(0.3, -0.2, 1.0), offset=(0.01, 0.02, 0.05))),
                                           ("pose_target", {})])
def test_selfcal_device_gradients_match_central_differences(kind, options):
    """jacfwd of the core's weighted residual w.r.t. robot and device parameters vs central differences
    (h = 1e-6, float64): relative error < 1e-6 (measured ~1e-10 both). Aim-line readings hold NaN where a
    sample knows nothing (aims at each of 3 targets, one distance sample)."""
    import jax
    from conftest import central_fd, rel_err

    from jaxcal.fit.core import residuals

    rb = jc.robots.get("stanford")
    dev = jc.make_device(kind, **options)
    q = jc.random_configurations(rb, 7, seed=3)
    a = np.asarray(jc.perturb(rb, 1e-3, seed=2))
    if kind == "aim_line":
        y = np.stack([dev.aim_reading(i % 3) for i in range(6)] + [dev.distance_reading({(0, 1): 0.4, (1, 2): 0.5})])
        d = np.array([0.5, 0.2, 0.3, 0.1, -0.4, 0.6, 0.7, 0.0, -0.2])
    else:
        y = np.asarray(jc.simulate(rb, rb.nominal, q, dev, device_params=np.array([0.3, -0.1, 0.2, 0.4, -0.5, 0.6])).y)
        d = np.array([0.31, -0.12, 0.19, 0.41, -0.52, 0.58])
    w = jnp.ones((len(q),) + (len(dev.residual_components),))
    f = jax.jit(lambda x: residuals(rb, dev, x, jnp.asarray(q), jnp.asarray(y), w).reshape(-1))
    x0 = np.concatenate([a, d])
    J = np.asarray(jax.jacfwd(f)(jnp.asarray(x0)))
    err = rel_err(J, central_fd(lambda x: f(jnp.asarray(x)), x0))
    assert np.all(np.isfinite(J)) and np.abs(J).max() > 0 and err < 1e-6, err
