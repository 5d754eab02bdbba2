"""Rotations: PRY (seed 000 eq 3.15-3.21, Table 3.1), Euler parameters (seed 004 A.15-A.19),
log/exp and pose differences (seed 001 Appendix I)."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from conftest import central_fd, rel_err

from jaxcal.kin import rotations as rt

QUADRANTS = np.deg2rad([45.0, 135.0, 225.0, 315.0])


def test_pry_composition_matches_eq_3_17():
    tx, ty, tz = 0.3, -0.7, 1.1
    R = np.asarray(rt.pry_to_matrix(jnp.array([tx, ty, tz])))
    c, s = np.cos, np.sin
    expected = np.array([
        [c(ty) * c(tz), -c(ty) * s(tz), s(ty)],
        [s(tx) * s(ty) * c(tz) + c(tx) * s(tz), -s(tx) * s(ty) * s(tz) + c(tx) * c(tz), -s(tx) * c(ty)],
        [-c(tx) * s(ty) * c(tz) + s(tx) * s(tz), c(tx) * s(ty) * s(tz) + s(tx) * c(tz), c(tx) * c(ty)],
    ])
    np.testing.assert_allclose(R, expected, atol=1e-15)


def _wrap_deg(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def test_table_3_1_reproduced_by_eq_3_19():
    """Table 3.1: where theta_y lies in the 2nd/3rd quadrant, the atan2 inverse (eq 3.19) returns
    (theta_x - 180, 180 - theta_y, theta_z - 180) (entries 'x(...)'), elsewhere the true angles ('-1')."""
    marked = 0
    for tx, ty, tz in itertools.product(QUADRANTS, repeat=3):
        R = rt.pry_to_matrix(jnp.array([tx, ty, tz]))
        got = np.rad2deg(np.asarray(rt.matrix_to_pry_atan2(R)))
        true = np.rad2deg([tx, ty, tz])
        if np.cos(ty) < 0:
            expected = _wrap_deg([true[0] - 180.0, 180.0 - true[1], true[2] - 180.0])
            marked += 1
        else:
            expected = _wrap_deg(true)
        np.testing.assert_allclose(_wrap_deg(got), expected, atol=1e-9)
    assert marked == 32
    # two entries read off the printed table
    R = rt.pry_to_matrix(jnp.deg2rad(jnp.array([45.0, 135.0, 45.0])))
    np.testing.assert_allclose(np.rad2deg(rt.matrix_to_pry_atan2(R)), [-135, 45, -135], atol=1e-9)
    R = rt.pry_to_matrix(jnp.deg2rad(jnp.array([135.0, 225.0, 315.0])))
    np.testing.assert_allclose(np.rad2deg(rt.matrix_to_pry_atan2(R)), [-45, -45, 135], atol=1e-9)


def test_acos_inverse_eq_3_18_fails_outside_first_quadrant_and_safe_inverse_never_does():
    acos_fail = 0
    for tx, ty, tz in itertools.product(QUADRANTS, repeat=3):
        R = rt.pry_to_matrix(jnp.array([tx, ty, tz]))
        safe = rt.matrix_to_pry(R)
        np.testing.assert_allclose(rt.pry_to_matrix(safe), R, atol=1e-12)  # always the same rotation
        assert abs(float(safe[1])) <= np.pi / 2  # the unique representative, -90 <= theta_y <= 90
        acos_fail += np.abs(np.asarray(rt.pry_to_matrix(rt.matrix_to_pry_acos(R)) - R)).max() > 1e-6
    assert acos_fail >= 56  # eq 3.18 holds only with all angles in its first-quadrant range


def test_safe_inverse_is_exact_near_theta_y_90_where_asin_form_loses_precision():
    for eps in (1e-8, 1e-9):
        ang = jnp.array([0.3, np.pi / 2 - eps, 0.2])
        R = rt.pry_to_matrix(ang)
        assert np.abs(np.asarray(rt.matrix_to_pry(R) - ang)).max() < 1e-14
        assert abs(float(rt.matrix_to_pry_atan2(R)[1] - ang[1])) > 0.5 * eps  # asin(r13) rounds to 90 deg


def test_quaternion_round_trip_and_half_turn(rng):
    for _ in range(50):
        w = rng.normal(size=3)
        R = rt.exp_so3(jnp.asarray(w))
        q = rt.quat_from_matrix(R)
        np.testing.assert_allclose(rt.matrix_from_quat(q), R, atol=1e-13)
        np.testing.assert_allclose(q, rt.quat_eigen(R), atol=1e-10)
    # half turns and near half turns, where eta0 -> 0 (seed 004 A.19 case)
    for axis in np.eye(3).tolist() + [[1 / np.sqrt(2), 1 / np.sqrt(2), 0.0]]:
        for ang in (np.pi, np.pi - 1e-9, np.pi - 1e-4):
            R = rt.exp_so3(jnp.asarray(axis) * ang)
            q = rt.quat_from_matrix(R)
            assert abs(np.linalg.norm(q) - 1) < 1e-12
            np.testing.assert_allclose(rt.matrix_from_quat(q), R, atol=1e-12)
            assert np.allclose(np.abs(q), np.abs(rt.quat_eigen(R)), atol=1e-8)


def test_log_exp_round_trip_including_zero_and_half_turn(rng):
    for w in [rng.normal(size=3) * s for s in (1e-9, 1e-3, 1.0, 3.0)] + [np.array([0.0, 0.0, np.pi])]:
        R = rt.exp_so3(jnp.asarray(w))
        np.testing.assert_allclose(rt.exp_so3(rt.log_so3(R)), R, atol=1e-11)
    # derivative of log at the identity is finite and equals vect's (the identity map on w)
    J = jax.jacfwd(lambda w: rt.log_so3(rt.exp_so3(w)))(jnp.zeros(3))
    np.testing.assert_allclose(J, np.eye(3), atol=1e-12)


def test_pose_difference_two_methods_agree_for_small_rotations(rng):
    Rj = rt.exp_so3(jnp.asarray(rng.normal(size=3)))
    d = jnp.asarray(rng.normal(size=3) * 1e-4)
    Ri = rt.exp_so3(d) @ Rj
    cross = rt.rotation_difference_cross(Ri, Rj)
    log = rt.rotation_difference_log(Ri, Rj)
    np.testing.assert_allclose(log, d, atol=1e-15 + 1e-12)
    assert rel_err(cross, d) < 1e-4  # eq 22 is first order
    v = rt.pose_difference(Ri, jnp.ones(3), Rj, jnp.zeros(3))
    np.testing.assert_allclose(v[:3], 1.0)


def test_rotation_gradients_match_central_differences(rng):
    x = rng.normal(size=3)
    for f in (rt.pry_to_matrix, rt.exp_so3, lambda v: rt.quat_from_matrix(rt.exp_so3(v)),
              lambda v: rt.log_so3(rt.exp_so3(v))):
        J = np.asarray(jax.jacfwd(f)(jnp.asarray(x))).reshape(-1, 3)
        assert rel_err(J, central_fd(f, x)) < 1e-7


def test_principal_rotation_is_rot_x_y_z_on_the_host():
    """The numpy rotations for host constants equal rot_x / rot_y / rot_z (1e-15) at any angle."""
    for angle in np.random.default_rng(3).uniform(-4, 4, 5):
        for axis, rot in enumerate((rt.rot_x, rt.rot_y, rt.rot_z)):
            R = rt.principal_rotation(axis, angle)
            assert isinstance(R, np.ndarray) and np.allclose(R, np.asarray(rot(angle)), rtol=0, atol=1e-15)
