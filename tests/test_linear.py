"""The linear formulation of seed 000 ch. 4 on MRR-1 (ch. 6.1): error model, pseudo-inverse, the
loop of Figure 4.1 and the four categories of Table 4.1 with their two failure modes."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.fit.linear import (
    apply_increment,
    chain_of,
    error_jacobian,
    linear_calibrate,
    orientation_error_pry,
    orientation_error_vect,
    pseudo_inverse_step,
    tip_pose,
)
from jaxcal.kin.conventions import pry_motion
from jaxcal.kin.rotations import exp_so3, pry_to_matrix, vect

# seed 000 Table 6.6: the "actual" MRR-1 tip pose at the Table 6.1 joint motions (home).
P_ACTUAL = np.array([0.42722476, 0.65018508, 0.25310769])
R_ACTUAL = np.array([[-1.8588651e-4, -9.9999914e-1, 1.2975389e-3],
                     [-9.9998926e-1, 1.7987616e-4, -4.6306960e-3],
                     [4.6304586e-3, -1.2983857e-3, -9.9998844e-1]])


@pytest.fixture(scope="module")
def mrr1():
    return jc.robots.get("mrr1")


@pytest.fixture(scope="module")
def home(mrr1):
    return np.asarray(mrr1.home)[None]


def test_module_chain_matches_forward(mrr1):
    chain, st = chain_of(mrr1)
    a = np.asarray(jc.perturb(mrr1, 0.05, seed=4))
    rows = a.reshape(3, 6)
    Rs = jax.vmap(pry_to_matrix)(jnp.asarray(rows[:, 3:]))
    Q = jc.random_configurations(mrr1, 5, seed=1)
    R, p = jax.vmap(lambda q: tip_pose(chain, jnp.asarray(rows[:, :3]), Rs, q))(jnp.asarray(Q))
    ref = jc.forward(mrr1, jnp.asarray(a), Q)
    assert np.abs(np.asarray(p - ref.p)).max() < 1e-15 and np.abs(np.asarray(R - ref.R)).max() < 1e-15


@pytest.mark.parametrize("update", ["pry", "skew"])
def test_error_jacobian_matches_central_fd(mrr1, update):
    """Pose-scheme J (6m x 18) against central differences of the incremented model; measured ~1e-10."""
    chain, st = chain_of(mrr1)
    Q = jnp.asarray(jc.random_configurations(mrr1, 4, seed=2))
    bs, th, Rs = jnp.asarray(st.bs + 0.01), jnp.asarray(st.theta + 0.02), jax.vmap(pry_to_matrix)(jnp.asarray(st.theta + 0.02))
    J = np.asarray(error_jacobian(chain, bs, th, Rs, Q, scheme="pose", update=update))
    Rn = jax.vmap(lambda q: tip_pose(chain, bs, Rs, q)[0])(Q)

    @jax.jit
    def model(dg):
        b2, _, R2 = apply_increment(bs, th, Rs, dg.reshape(3, 6), update)
        R, p = jax.vmap(lambda q: tip_pose(chain, b2, R2, q))(Q)
        return jnp.concatenate([p, jax.vmap(lambda a, b: vect(a @ b.T))(R, Rn)], axis=1).reshape(-1)

    fd = central_fd(lambda x: model(jnp.asarray(x)), np.zeros(18))
    assert rel_err(J, fd) < 1e-8


def _geometric_jacobian(chain, bs, Rs, q):
    """Hand-derived eq 4.3b: per module [x_i y_i z_i, x_i x p_i, y_i x p_i, z_i x p_i; 0, x_i y_i z_i],
    with (x_i, y_i, z_i) the columns of R_0i and p_i the vector from module i's origin to the tip."""
    R, p, frames = np.asarray(chain.base_R), np.asarray(chain.base_p), []
    for i, kind in enumerate(chain.kinds):
        Rm, bm = pry_motion(kind, jnp.asarray(q[i:i + 1]))
        R = R @ np.asarray(Rs[i]) @ np.asarray(Rm)
        frames.append((R, p))
        p = p + R @ (np.asarray(bs[i]) + np.asarray(bm))
    cols = []
    for R0i, o in frames:
        lever = p - o
        top = np.hstack([R0i, np.stack([np.cross(R0i[:, k], lever) for k in range(3)], 1)])
        cols.append(np.vstack([top, np.hstack([np.zeros((3, 3)), R0i])]))
    return np.hstack(cols)


def test_moving_axes_jacobian_is_eq_4_3b(mrr1):
    """Autodiff J about the moving axes equals the seed's geometric Jacobian (independent check)."""
    chain, st = chain_of(mrr1)
    Q = jc.random_configurations(mrr1, 3, seed=5)
    J = np.asarray(error_jacobian(chain, jnp.asarray(st.bs), jnp.asarray(st.theta), jnp.asarray(st.Rs), jnp.asarray(Q),
                                  scheme="pose", update="pry", axes="moving"))
    G = np.vstack([_geometric_jacobian(chain, st.bs, st.Rs, q) for q in Q])
    assert np.abs(J - G).max() < 1e-14


def test_pseudo_inverse_is_eq_4_26_and_4_27(rng):
    J = rng.standard_normal((6, 18))  # one pose: under-determined, minimum norm (eq 4.26)
    dX = rng.standard_normal(6)
    np.testing.assert_allclose(pseudo_inverse_step(J, dX), J.T @ np.linalg.solve(J @ J.T, dX), atol=1e-12)
    J = rng.standard_normal((60, 18))  # many poses: least squares (eq 4.27)
    dX = rng.standard_normal(60)
    np.testing.assert_allclose(pseudo_inverse_step(J, dX), np.linalg.solve(J.T @ J, J.T @ dX), atol=1e-12)


def test_position_calibration_table_6_6_converges_like_figure_6_6(mrr1, home):
    """Seed ch. 6.1: position-only calibration at one pose, RMSPE 3.8e-3 m -> 6.2e-7 m in 4 iterations.

    The engine starts at RMSPE 3.794e-3 m (Table 6.6 actual vs nominal). With the seed's geometric
    Jacobian (rotations about the moving axes, eq 4.3b) applied to R_s it falls linearly,
    3.79e-3 -> 3.2e-4 -> 4.3e-5 -> 4.4e-6 -> 4.6e-7 m (skew update): below 1e-6 at iteration 4 as in
    the seed (PRY update: 1.5e-7 at iteration 5). With J of the update's own increments (autodiff)
    the step is Newton's: 3.79e-3 -> 6e-6 -> 1e-11, two iterations."""
    runs = {(axes, upd): linear_calibrate(mrr1, home, None, P_ACTUAL[None], "position", update=upd, axes=axes, tol=1e-6)
            for axes in ("static", "moving") for upd in ("pry", "skew")}
    for r in runs.values():
        assert r.rmspe[0] == pytest.approx(3.794e-3, rel=1e-3)
        assert r.converged and r.iterations <= 6 and r.rmspe[-1] < 1e-6
    seed_like = runs[("moving", "skew")]
    assert seed_like.iterations == 4 and 1e-7 < seed_like.rmspe[-1] < 1e-6
    assert np.all(np.diff(np.log(seed_like.rmspe)) < -1.5)  # linear rate, ~10x per iteration
    assert runs[("static", "pry")].iterations == 2 and runs[("static", "skew")].iterations == 2


def test_table_6_5_is_nearer_the_minimum_norm_step_in_degrees(mrr1, home):
    """One pose leaves 7 of the 18 errors undetermined, so the identified errors (Table 6.5) are the
    pseudo-inverse's minimum-norm choice, which depends on the unit of the angles. Measured on the Table 6.6
    pose: in m and rad dx1 = -1.342e-3; in m and deg -1.640e-3 (seed -1.6453e-3), dz +-1.036e-3 on all three
    modules (seed +-9.88e-4), dy2 = dy3 = 1.929e-3 (seed 1.913e-3). The seed's angle errors (5e-5 .. 6.7e-4
    rad) are not those of either choice (ours in degrees: < 1e-6 rad), so Table 6.5 is not reproduced."""
    seed_dx1 = -1.6453e-3
    rad = linear_calibrate(mrr1, home, None, P_ACTUAL[None], "position", tol=1e-12)
    deg = linear_calibrate(mrr1, home, None, P_ACTUAL[None], "position", tol=1e-12, angle_scale=np.pi / 180)
    for r in (rad, deg):
        assert r.rmspe[-1] < 1e-12
    nominal = np.asarray(mrr1.nominal_np).reshape(3, 6)
    d_rad, d_deg = rad.a.reshape(3, 6) - nominal, deg.a.reshape(3, 6) - nominal
    assert abs(d_deg[0, 0] - seed_dx1) < 1e-5 < abs(d_rad[0, 0] - seed_dx1)
    np.testing.assert_allclose(np.abs(d_deg[:, 2]), 1.036e-3, rtol=2e-3)
    assert d_deg[1, 1] == pytest.approx(d_deg[2, 1], abs=1e-12) and d_deg[1, 1] == pytest.approx(1.929e-3, rel=2e-3)
    assert np.max(np.abs(d_deg[:, 3:])) < 1e-6 < np.max(np.abs(d_rad[:, 3:]))


def test_rmsoe_is_nan_without_measured_rotations(mrr1, home):
    """Position scheme from positions only: there is no measured orientation, so RMSOE is NaN at every
    iteration (not the error against a stand-in identity rotation); given R_meas it is the real
    orientation error (eq 4.31) although the position scheme does not fit it."""
    without = linear_calibrate(mrr1, home, None, P_ACTUAL[None], "position", tol=1e-6)
    assert without.converged and np.all(np.isnan(without.rmsoe)) and len(without.rmsoe) == len(without.rmspe)
    with_r = linear_calibrate(mrr1, home, R_ACTUAL[None], P_ACTUAL[None], "position", tol=1e-6)
    np.testing.assert_array_equal(with_r.rmspe, without.rmspe)
    R_nominal = np.asarray(jc.forward(mrr1, mrr1.nominal, home).R)[0]
    angle = np.arccos(np.clip((np.trace(R_ACTUAL @ R_nominal.T) - 1) / 2, -1, 1))
    assert np.isfinite(with_r.rmsoe).all()
    assert with_r.rmsoe[0] == pytest.approx(angle / np.sqrt(3), rel=1e-4)  # RMS of a 3-vector = norm / sqrt 3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_position_calibration_converges_within_6_for_random_errors(mrr1, seed):
    """Errors drawn N(0, 0.003) on all 18 module parameters (Table 6.3), 8 random poses, noise-free,
    PRY update (eq 4.29) with J of its own increments: converges in 2 iterations (measured, seeds 0-3).
    J has rank 11 of 18 (the module parameters are redundant for position): the SVD pseudo-inverse
    takes the minimum-norm step in the identifiable subspace."""
    a_true = jc.perturb(mrr1, 0.003, seed=seed)
    Q = jc.random_configurations(mrr1, 8, seed=10 + seed)
    p = np.asarray(jc.forward(mrr1, a_true, Q).p)
    r = linear_calibrate(mrr1, Q, None, p, "position", update="pry", tol=1e-6)
    assert r.converged and r.iterations <= 6, r.rmspe
    assert np.all(r.rank == 11)
    np.testing.assert_allclose(np.asarray(jc.forward(mrr1, jnp.asarray(r.a), Q).p), p, atol=1e-6)


def test_skew_update_ill_conditions_J_and_diverges_with_many_poses(mrr1):
    """Seed §4.3.2: after the skew update (eq 4.30) 'the orthogonality of the static rotation matrix is
    slightly sacrificed, and it may cause the ill-conditioning of the Jacobian ... non-convergence'.
    Measured (8 poses, seed 1): the first step cuts RMSPE 4.7e-3 -> 1.2e-5 m but leaves
    ||R_s^T R_s - I|| = 3.5e-5; J's structural null space (rank 11) gains a 12th singular value at
    ~5e-8 s_1 (condition of the used part 32 -> 2.0e7), the pseudo-inverse divides by it and the
    next step (6 m/rad) diverges. The seed's own
    Jacobian (moving axes, eq 4.3b) diverges here too: its rotation axes turn with the joint angle, so
    with poses at different joint angles it is no model of constant module errors."""
    a_true = jc.perturb(mrr1, 0.003, seed=1)
    Q = jc.random_configurations(mrr1, 8, seed=11)
    p = np.asarray(jc.forward(mrr1, a_true, Q).p)
    r = linear_calibrate(mrr1, Q, None, p, "position", update="skew", tol=1e-6)
    assert not r.converged and r.rmspe[1] < 1e-4 and r.rmspe[2] > 1e-3
    assert r.rank[0] == 11 and r.rank[1] == 12 and r.condition[1] > 1e5 * r.condition[0]  # measured 32 -> 2.0e7
    assert r.orthogonality[1] > 1e-5
    seed_j = linear_calibrate(mrr1, Q, None, p, "position", update="pry", axes="moving", tol=1e-6)
    assert not seed_j.converged and seed_j.rmspe[-1] > seed_j.rmspe[0]


def test_skew_update_loses_orthogonality(mrr1, home):
    """Category 1 (vect, skew: eq 4.30) leaves ||R_s^T R_s - I|| ~ 7e-6 after the first update; category 3
    (vect, PRY angles: eq 4.29) keeps it at rounding level. Both fit the one pose of Table 6.6."""
    cat1 = linear_calibrate(mrr1, home, R_ACTUAL[None], P_ACTUAL[None], "pose", category=1, tol=1e-12)
    cat3 = linear_calibrate(mrr1, home, R_ACTUAL[None], P_ACTUAL[None], "pose", category=3, tol=1e-12)
    assert cat1.converged and cat3.converged
    assert cat1.orthogonality[0] < 1e-15 and np.all(cat1.orthogonality[1:] > 1e-6)
    assert np.all(cat3.orthogonality < 1e-14)
    Rs = cat1.state.Rs
    assert np.abs(np.linalg.det(Rs) - 1).max() > 1e-7  # no longer a rotation


def test_pry_difference_breaks_at_mrr1_tip_and_skew_category_diverges(mrr1, home):
    """MRR-1's tip orientation is Rz(q1 + q2) Ry(180 deg): theta_x = +-180 deg, the branch cut of every
    atan2 inverse. The measured and nominal angles fall on opposite sides, so Phi (theta_m - theta_n)
    is off by ~2 pi while vect(delta) gives the true 4.6e-3 rad error: category 2 does not converge
    (Figure 6.7); category 4 wanders for several iterations (measured: RMSE 2.56 at the start)."""
    Rn = np.asarray(jc.forward(mrr1, mrr1.nominal, mrr1.home).R)
    wrong = np.asarray(orientation_error_pry(jnp.asarray(R_ACTUAL), jnp.asarray(Rn)))
    right = np.asarray(orientation_error_vect(jnp.asarray(R_ACTUAL), jnp.asarray(Rn)))
    assert np.linalg.norm(right) < 6e-3 and np.linalg.norm(wrong) > 6.0
    cat2 = linear_calibrate(mrr1, home, R_ACTUAL[None], P_ACTUAL[None], "pose", category=2, tol=1e-6, max_iter=20)
    assert not cat2.converged and cat2.rmse[-1] > 0.1
    cat4 = linear_calibrate(mrr1, home, R_ACTUAL[None], P_ACTUAL[None], "pose", category=4, tol=1e-6, max_iter=20)
    assert cat4.rmse[0] > 1.0 and cat4.iterations > 4


def test_pry_difference_quadrants_of_table_3_1():
    """Small rotation omega applied to R_n = R_pry(theta) with theta over the quadrants of Table 3.1
    (45, 135, 225, 315 deg each): vect recovers omega everywhere; the atan2 difference (eq 3.19)
    also does, since both angle sets land on the same (possibly equivalent, Table 3.1) branch; the
    arccos inverse (eq 3.18) fails in every octant but the first; at theta_x = 180 deg (a branch cut)
    both atan2 forms fail."""
    omega = 1e-4 * np.array([1.0, -2.0, 1.5])
    Rd = exp_so3(jnp.asarray(omega))
    fails = {"vect": 0, "atan2": 0, "acos": 0, "safe": 0}
    for ang in itertools.product(np.deg2rad([45.0, 135.0, 225.0, 315.0]), repeat=3):
        Rn = pry_to_matrix(jnp.asarray(ang))
        Rm = Rd @ Rn
        fails["vect"] += np.linalg.norm(np.asarray(orientation_error_vect(Rm, Rn)) - omega) > 1e-6
        for inv in ("atan2", "acos", "safe"):
            fails[inv] += np.linalg.norm(np.asarray(orientation_error_pry(Rm, Rn, inv)) - omega) > 1e-6
    assert fails["vect"] == fails["atan2"] == fails["safe"] == 0
    assert fails["acos"] >= 56
    Rn = pry_to_matrix(jnp.deg2rad(jnp.array([180.0, 10.0, 30.0])))
    for inv in ("atan2", "safe"):  # +-omega: one of the two crosses the cut and is off by ~2 pi
        worst = max(np.linalg.norm(np.asarray(orientation_error_pry(Rm, Rn, inv))) for Rm in (Rd @ Rn, Rd.T @ Rn))
        assert worst > 1.0
    assert np.linalg.norm(np.asarray(orientation_error_vect(Rd.T @ Rn, Rn)) + omega) < 1e-6


def test_bad_input(mrr1, home):
    with pytest.raises(ValueError, match="scheme"):
        linear_calibrate(mrr1, home, None, P_ACTUAL[None], "orientation")
    with pytest.raises(ValueError, match="needs measured rotations"):
        linear_calibrate(mrr1, home, None, P_ACTUAL[None], "pose")
    with pytest.raises(ValueError, match="category"):
        linear_calibrate(mrr1, home, None, P_ACTUAL[None], category=5)
    with pytest.raises(ValueError, match="m joint vectors"):
        linear_calibrate(mrr1, np.zeros((2, 3)), None, P_ACTUAL[None])
    with pytest.raises(ValueError, match="serial chain of PRY modules"):
        chain_of(jc.robots.get("stanford"))
