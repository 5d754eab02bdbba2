"""Mobility / constraint verdicts of seed 004 Figure 2.5 cases a-h (§2.5.2) on the four-bar of Table 4.2a.

Figure 2.5 gives only drawings and the verdicts (r vs the number of free joints, cond(psi)), not
the geometry of each case, so each case is built here from the Table 4.2a rows (joints 3 and 4
coincident at the second ground pivot, ball closure between 2 and 6, as in the figure's labels) with
the change the figure describes. The thesis' theta1 = 0 / pi singular settings (b, c) are
theta1 = -pi/2 / +pi/2 in the Table 4.2a frames, where the crank is collinear with the ground link.

Printed numbers reproduced: case a at theta1 = -0.4 (the 2-D example's pi/2 + 0.4 seen from the
other side) gives cond(psi) = 4.0227 (eq 2.102 text) and the third singular value 2.7281; case d
gives cond(psi) = 3.7417 as printed. The first two singular values of case a come out 2.9434 and
2.7891 against the printed 2.8971 and 2.8336: the null space (hence psi, N psi^-1 and the
closed-loop Jacobian) agrees, so the thesis' dv/da differs from ours by a non-orthogonal row
operation (how its position and Euler rows were scaled or expressed is not recoverable from the
OCR); we do not assert those two. Case b prints (2.8479, 2.3786, 2.2361), we get (3, 2.2361,
2.2361); its cond(psi) 1.99e12 is a numerical-zero pivot, ours ~1e16: both singular.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.closure import closure_residual, mobility, solve
from jaxcal.robots import mcpc_robot

H = np.pi / 2
TABLE_4_2A = [
    [0, 0, 0, 0, 0, 0, 0, 0, 0],
    [0, 0, 0, 0, 1, 0, 1, 0, 0],
    [0, 0, 0, 1, 0, 0, 0, 0, 0],
    [-H, 0, 0, 0, 0, 0, 3, 0, 0],
    [H, 0, 0, 0, 1, 0, 4, 0, 0],
    [-H, 0, 0, -1, 0, 0, 5, 2, 2],
]
T1 = -0.4


def _rows(body, field, value):
    rows = [list(r) for r in TABLE_4_2A]
    rows[body - 1][field] = value
    return rows


def _verdict(rows, actuated, q, theta_free):
    """Mobility at the closed configuration theta_free (exact, or closed by LM from it)."""
    rb = mcpc_robot("case", rows, actuated=actuated, closure_start=theta_free)
    q = jnp.asarray(q, dtype=jnp.float64)
    theta = jnp.asarray(theta_free, dtype=jnp.float64)
    if float(jnp.linalg.norm(closure_residual(rb, rb.nominal, q, theta))) > 1e-12:
        sol = solve(rb, rb.nominal, q)
        assert bool(sol.ok), float(sol.residual_norm)
        theta = sol.theta_free
    return mobility(rb, q=q, theta_free=theta)


def test_a_proper_nonsingular():
    m = mobility(jc.robots.get("fourbar3d"), q=jnp.array([T1]))
    assert (m.r, m.n_free, m.verdict) == (3, 3, "proper")
    assert abs(m.cond_psi - 4.0227) < 0.5e-4 and not m.near_singular
    assert abs(m.singular_values[2] - 2.7281) < 0.5e-4
    assert m.actuator_motion[0] > 0.5


@pytest.mark.parametrize("theta1, theta_free", [(-H, (-H, 0.0, H)), (H, (H, 0.0, -H))])
def test_b_c_singular_positions(theta1, theta_free):
    """b: crank onto the ground link (joints 2 and 4 coincide); c: links stretched. r = 3, psi ill-conditioned."""
    m = _verdict(TABLE_4_2A, [1], [theta1], theta_free)
    assert (m.r, m.verdict) == (3, "proper") and m.near_singular and m.cond_psi > 1e10


def test_d_actuator_zero_length():
    """Proper and well conditioned, but the actuator moves nothing (its closed-loop column is zero)."""
    m = _verdict(_rows(2, 4, 0.0), [1], [T1], (0.0, 2 * np.pi / 3, 2 * np.pi / 3))
    assert (m.r, m.verdict) == (3, "proper") and not m.near_singular
    assert abs(m.cond_psi - 3.7417) < 0.5e-4
    assert m.actuator_motion[0] < 1e-10


def test_e_link_zero_length():
    """Link 4-5 of zero length: closable only at theta1 = -pi/6; r = 3, psi singular."""
    m = _verdict(_rows(5, 4, 0.0), [1], [-np.pi / 6], (-np.pi / 6, 0.0, np.pi / 3))
    assert (m.r, m.verdict) == (3, "proper") and m.near_singular


def test_f_too_many_actuators():
    """Joints 1 and 3 actuated: free joints 4 and 5 but r = 3 -> over-constrained."""
    m = _verdict(TABLE_4_2A, [1, 3], [T1, T1], (0.0, -T1))
    assert (m.r, m.n_free, m.verdict) == (3, 2, "over-constrained")


def test_g_truss():
    """An extra member from a third ground pivot to joint 2 (second ball closure 2-8): 4 free joints, r = 6."""
    p2 = np.array([-np.sin(T1), np.cos(T1)])
    rows = [list(r) for r in TABLE_4_2A] + [[0, 0, 0, 0, -1, 0, 0, 0, 0], [0, 0, 0, p2[0], p2[1] + 1, 0, 7, 2, 2]]
    m = _verdict(rows, [1], [T1], (T1, 0.0, -T1, 0.0))
    assert (m.r, m.n_free, m.verdict) == (6, 4, "over-constrained")


def test_h_extra_link_underconstrained():
    """Link 5-6 split by an extra free rotary joint: 4 free joints, r = 3 -> under-constrained."""
    rows = [list(r) for r in TABLE_4_2A[:5]] + [[0, 0, 0, -0.5, 0, 0, 5, 0, 0], [-H, 0, 0, -0.5, 0, 0, 6, 2, 2]]
    m = _verdict(rows, [1], [T1], (T1, 0.0, -T1, 0.0))
    assert (m.r, m.n_free, m.verdict) == (3, 4, "under-constrained")


def test_planar_fourbar_is_proper():
    m = mobility(jc.robots.get("fourbar2d"))
    assert (m.r, m.n_free, m.verdict) == (2, 2, "proper") and not m.near_singular
