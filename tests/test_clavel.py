"""Clavel's direct solution of the Delta and its breakdown ratio K_crit (seed 004 eq 2.118-2.134),
and the open-loop Jacobian check of §2.4.3 (210 x 124).

The fast tests hold Clavel's solution to the thesis' variation (`delta.direct`, itself held to the
general closure to 1e-12 in tests/test_delta.py); the slow ones compare with the general closure
(`jc.forward` on the 30-body tree) directly and need the Delta model (~30 s of loading and compiling)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import clavel as cl
from jaxcal.closure import delta as dl
from jaxcal.kin.model import joint_variables

_clavel = jax.jit(jax.vmap(cl.direct))
_variation = jax.jit(jax.vmap(dl.direct))
_k_crit = jax.jit(jax.vmap(cl.k_crit))
_h2 = jax.jit(jax.vmap(lambda t: cl.h_terms(*cl.sphere_coefficients(t))[1]))

K_R = (0.2805 - 0.196) / 0.6  # Table 4.6: (rb - rn) / n = 0.1408
DELTAS = np.array([1e-2, 1e-3, 1e-6, 1e-9, 1e-10])  # offsets of theta_1 from the h2 = 0 surface


@pytest.fixture(scope="module")
def rb():
    return jc.robots.get("delta")


def _near_singular():
    """Settings theta_1 = theta_1* + delta, theta_2 = theta_3 = 1.4 (the joint limit): with u_i = K + cos theta_i,
    h2 ~ u1 u2 + u2 u3 + u3 u1 vanishes at u1 = -u2 / 2, i.e. theta_1* = 107.2 deg (an assembly the
    nominal closure still solves)."""
    t1 = np.arccos(-(K_R + np.cos(1.4)) / 2 - K_R)
    return np.array([[t1 + d, 1.4, 1.4] for d in DELTAS])


@pytest.fixture(scope="module")
def closed_tool(rb):
    """One call of the general closure for 48 random settings in the joint limits and the near-singular ones."""
    random = np.random.default_rng(7).uniform(-0.2, 1.4, (48, 3))
    theta = jnp.asarray(np.concatenate([random, _near_singular()]))
    return theta, jc.forward(rb, dl.full_precision_nominal(rb), theta).p


def test_clavel_matches_variation_in_the_joint_limits():
    theta = jnp.asarray(np.random.default_rng(5).uniform(-0.2, 1.4, (2000, 3)))
    mine, ok = _clavel(theta)
    P, ok_v = _variation(theta)
    assert bool(jnp.all(ok)) and bool(jnp.all(ok_v))
    assert float(jnp.max(jnp.abs(mine - P))) < 1e-12


def test_accuracy_is_lost_as_h2_goes_to_zero():
    """Error ~ 1e-20 / h2^2 (m) against the variation (which does not break down there): 1e-12 at
    |h2| >= 2e-3, then the wrong point (0.1 m to km off, flag set or not) once |h2| < 2e-10."""
    theta = jnp.asarray(_near_singular())
    mine, _ = _clavel(theta)
    err = np.asarray(jnp.max(jnp.abs(mine - _variation(theta)[0]), axis=1))
    h2 = np.abs(np.asarray(_h2(theta)))
    assert np.all(np.diff(h2) < 0) and h2[0] > 1e-3 and h2[-1] < 1e-10
    assert err[0] < 1e-12 and err[1] < 1e-11
    assert err[2] / err[1] > 1e4  # h2 1000 x smaller: error >= 1e4 x larger
    assert err[3] > 1e-3 and err[4] > 1e-3


@pytest.mark.slow
def test_clavel_matches_general_closure(closed_tool):
    """(A sample the closure cannot close is moved 1e3 m away by `failed_pose`: agreement means closed.)"""
    theta, P = closed_tool
    mine, feasible = _clavel(theta[:48])
    assert bool(jnp.all(feasible))
    assert float(jnp.max(jnp.abs(mine - P[:48]))) < 1e-12


def test_clavel_derivative_against_central_differences():
    theta = np.random.default_rng(3).uniform(0.0, 1.2, (4, 3))
    for t in theta:
        J = np.asarray(jax.jacfwd(lambda x: cl.direct(x)[0])(jnp.asarray(t)))
        assert rel_err(J, central_fd(lambda x: np.asarray(cl.direct(jnp.asarray(x))[0]), t)) < 1e-8


def test_h2_is_quadratic_in_the_design_ratio():
    """Eq 2.124 from the sphere coefficients equals n^2 times eq 2.133 at K = (rb - rn) / n, and the
    roots of eq 2.134 zero it."""
    theta = jnp.asarray(np.random.default_rng(4).uniform(-np.pi, np.pi, (200, 3)))
    assert abs(cl.design_ratio() - K_R) < 1e-15
    eq_2_133 = jax.vmap(lambda t: cl.h2_of_ratio(t, K_R))(theta) * 0.6**2
    assert float(jnp.max(jnp.abs(_h2(theta) - eq_2_133))) < 1e-14
    lo, hi = _k_crit(theta)
    for root in (lo, hi):
        assert float(jnp.max(jnp.abs(jax.vmap(cl.h2_of_ratio)(theta, root)))) < 1e-12


def test_k_crit_maximum_over_the_workspace():
    """K_crit,1 = -min cos theta: 1.0 over a full turn of the arms (the thesis' 'K > 1.0 is non-singular'),
    -0.170 over the joint limits [-0.2, 1.4] rad, below Table 4.6's K_r = 0.141."""
    for lo, hi, want in [(-np.pi, np.pi, 1.0), (-0.2, 1.4, -np.cos(1.4))]:
        _, k = _k_crit(jnp.asarray(cl.actuator_box(lo, hi, 33)))
        assert abs(float(jnp.max(k)) - want) < 1e-12
        assert abs(cl.k_crit_max_bound(lo, hi) - want) < 1e-15


def test_beyond_k_crit_max_the_solution_never_breaks_down():
    """Over a full turn of all three arms (33^3 settings): with K = 1.2 > K_crit,1 = 1, h2 keeps one sign
    (|h2| / n^2 >= 3 sqrt 3 / 2 x 0.2^2) and Clavel's solution equals the variation wherever both are
    feasible; with Table 4.6's K = 0.141 h2 changes sign."""
    box = jnp.asarray(cl.actuator_box(-np.pi, np.pi, 33))
    wide = dl.DeltaGeometry(rb=0.196 + 1.2 * 0.6)
    h2 = jax.vmap(lambda t: cl.h2_of_ratio(t, 1.2))(box)
    assert float(jnp.min(jnp.abs(h2))) >= 1.5 * np.sqrt(3) * 0.2**2 - 1e-12 and float(jnp.min(h2 * jnp.sign(h2[0]))) > 0
    P, ok = jax.vmap(lambda t: cl.direct(t, wide))(box)
    Pv, okv = jax.vmap(lambda t: dl.direct(t, wide))(box)
    both = ok & okv
    assert int(jnp.sum(both)) > 1000
    assert float(jnp.max(jnp.where(both[:, None], jnp.abs(P - Pv), 0.0))) < 1e-11
    h2_nominal = jax.vmap(lambda t: cl.h2_of_ratio(t, K_R))(box)
    assert float(jnp.min(h2_nominal)) < 0 < float(jnp.max(h2_nominal))


@pytest.mark.slow
def test_general_closure_near_h2_zero(closed_tool):
    """Near h2 = 0 the general closure agrees with the variation (1e-13) and Clavel's error is as in
    `test_accuracy_is_lost_as_h2_goes_to_zero`."""
    theta, P = closed_tool
    assert float(jnp.max(jnp.abs(_variation(theta[48:])[0] - P[48:]))) < 1e-13
    err = np.asarray(jnp.max(jnp.abs(_clavel(theta[48:])[0] - P[48:]), axis=1))
    assert err[0] < 1e-12 and err[3] > 1e-3


@pytest.mark.slow
def test_open_loop_jacobian_of_section_2_4_3(rb):
    """All 30 frames (position + Euler parameters) of the open tree at the closed home configuration,
    against the 124 geometric parameters: 210 x 124, full rank, condition ~41 (thesis: 101); autodiff vs
    central differences (h = 1e-6) to 1e-9, vs forward differences (h = 1e-4) ~5e-5 (thesis: 2e-5)."""
    a = rb.nominal
    qj = joint_variables(rb, a, jnp.asarray(rb.home_np))
    theta_free = jnp.asarray(rb.closure.start)
    cols = dl.open_loop_columns(rb)
    vec = jax.jit(lambda x: dl.open_loop_vector(rb, x, qj, theta_free))
    J = np.asarray(jax.jit(jax.jacfwd(lambda x: dl.open_loop_vector(rb, x, qj, theta_free)))(a))[:, cols]
    assert J.shape == (210, 124)

    def vec_cols(x):
        full = np.array(a)
        full[cols] = x
        return np.asarray(vec(jnp.asarray(full)))

    x0 = np.asarray(a)[cols]
    assert np.max(np.abs(J - central_fd(vec_cols, x0, h=1e-6))) < 1e-9
    forward = np.stack([(vec_cols(x0 + 1e-4 * e) - vec_cols(x0)) / 1e-4 for e in np.eye(124)], axis=1)
    assert 1e-5 < np.max(np.abs(J - forward)) < 1e-4
    s = np.linalg.svd(J, compute_uv=False)
    assert s[-1] > 0.1 and 20 < s[0] / s[-1] < 100
