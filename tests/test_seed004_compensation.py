"""Seed 004 compensation (implementation): the exact least-squares solve, the thesis' fast
line-search method (§3.2, §4.4.4), the Kiwibot's orientation target with the strut-length bias
(§4.3), and the Table 4.7 analyses of the Delta (§4.4.4; slow: compile through the closure).
Study and numbers: benchmarks/seed004_compensation.py, docs/seed004-compensation.md."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.closure import delta as dl
from jaxcal.closure import kiwibot as kb
from jaxcal.fit.compensate import least_squares, line_search
from jaxcal.kin.rotations import log_so3


def central_fd(f, x, h=1e-6):
    f = jax.jit(f)
    cols = [(f(x.at[i].add(h)) - f(x.at[i].add(-h))) / (2 * h) for i in range(x.shape[0])]
    return jnp.stack(cols, axis=-1)


def test_line_search_is_exact_on_a_linear_residual():
    """For r = A q - b, f is quadratic along d = -A^T r0, so the quadratic interpolation gives the
    exact steepest-descent minimiser t* = |d|^2 / |A d|^2, whatever the offsets."""
    A = jnp.array([[2.0, 0.3, 0.0], [0.1, 1.0, 0.4], [0.0, 0.2, 0.5], [0.3, 0.0, 1.5]])
    b = jnp.array([1.0, -2.0, 0.5, 0.3])
    q0 = jnp.array([0.2, 0.1, -0.3])
    d = -A.T @ (A @ q0 - b)
    expected = q0 + (d @ d) / jnp.sum((A @ d) ** 2) * d
    assert float(jnp.max(jnp.abs(line_search(lambda q: A @ q - b, q0) - expected))) < 1e-12


def kiwibot_target(theta):
    pose = kb.direct(theta)
    return pose.R, jnp.linalg.norm(pose.p)


def test_kiwibot_pointing_residual_jacfwd_matches_finite_differences():
    """d r / d theta of the §4.3 residual through the analytic direct solution, away from its zero."""
    R, s = kiwibot_target(jnp.array([0.6, 0.4, 0.7]))
    f = lambda q: kb.pointing_residual(kb.direct(q), R, s)  # noqa: E731
    q = jnp.array([0.55, 0.45, 0.65])
    J = jax.jit(jax.jacfwd(f))(q)
    assert float(jnp.max(jnp.abs(J - central_fd(f, q)))) < 1e-8 * float(jnp.max(jnp.abs(J)))


def test_kiwibot_orientation_compensation_finds_a_reachable_target():
    """A pose the (here analytic nominal) model reaches is found exactly from 0.1 rad away, and the
    strut bias pins the plunging freedom: without it (w = 0) the 3 orientation equations alone
    leave the strut free and the same start lands elsewhere along it."""
    theta = jnp.array([0.3, 0.8, 0.5])
    R, s = kiwibot_target(theta)
    start = theta + jnp.array([0.1, -0.1, 0.1])
    q = jax.jit(lambda x: least_squares(lambda y: kb.pointing_residual(kb.direct(y), R, s), x))(start)
    assert float(jnp.max(jnp.abs(q - theta))) < 1e-10
    q_free = jax.jit(lambda x: least_squares(lambda y: kb.pointing_residual(kb.direct(y), R, s, weight=0.0), x))(start)
    pose = kb.direct(q_free)
    assert float(jnp.linalg.norm(log_so3(R.T @ pose.R))) < 1e-9  # orientation met ...
    assert abs(float(jnp.linalg.norm(pose.p) - s)) > 1e-3  # ... at another strut length


# A "calibrated" analytic Delta whose rods are 20 mm longer than nominal: the nominal inverse misses by
# centimetres, the exact solve puts the tool on target, the fast method gets part of the way.
LONG = dl.DeltaGeometry(m=0.92)
TARGETS = jnp.asarray(dl.grid())


def delta_residual(target):
    return lambda q: dl.direct(q, LONG)[0] - target


def test_fast_method_against_exact_on_the_grid():
    """§4.4.4: exact (Gauss-Newton) to < 1e-9 m on all 125 grid points; the single line search cuts
    the worst error of the nominal inverse solution by more than half but leaves millimetres
    (thesis: 13.4 mm fast vs 9.32 mm exact on the real robot's model)."""
    q0 = jax.jit(jax.vmap(dl.inverse))(TARGETS)[0]
    err = jax.jit(lambda q: jnp.linalg.norm(jax.vmap(lambda x, t: delta_residual(t)(x))(q, TARGETS), axis=-1))
    exact = jax.jit(jax.vmap(lambda t, q: least_squares(delta_residual(t), q)))(TARGETS, q0)
    fast = jax.jit(jax.vmap(lambda t, q: line_search(delta_residual(t), q)))(TARGETS, q0)
    before, e_exact, e_fast = float(jnp.max(err(q0))), float(jnp.max(err(exact))), float(jnp.max(err(fast)))
    assert before > 0.01 and e_exact < 1e-9
    assert 1e-4 < e_fast < 0.5 * before, (before, e_fast)


def test_line_search_jacfwd_matches_finite_differences():
    """The fast method's settings as a function of the target (smooth where the vertex is interior)."""
    q0 = dl.inverse(TARGETS[7])[0]
    f = lambda t: line_search(delta_residual(t), q0)  # noqa: E731
    J = jax.jit(jax.jacfwd(f))(TARGETS[7])
    assert float(jnp.max(jnp.abs(J - central_fd(f, TARGETS[7])))) < 1e-6 * float(jnp.max(jnp.abs(J)))


@pytest.fixture(scope="module")
def delta_study():
    import jaxcal as jc
    from jaxcal.fit.compensate import compensate

    rb = jc.robots.get("delta")
    a_true = dl.thesis_perturbed(rb)
    q0 = jax.vmap(dl.inverse)(TARGETS)[0]
    R_ref = jc.forward(rb, rb.nominal, q0).R

    def judged(q):
        pose = jc.forward(rb, a_true, q)
        worst = float(jnp.max(jnp.linalg.norm(pose.p - TARGETS, axis=-1))) * 1e3
        angle = float(jnp.max(jnp.linalg.norm(jax.vmap(lambda R, Rr: log_so3(Rr.T @ R))(pose.R, R_ref), axis=-1)))
        return worst, np.degrees(angle)

    a_exp = dl.thesis_identified(rb, "experiment")
    fast = jax.vmap(lambda t, q: line_search(lambda x: jc.forward(rb, a_exp, x).p - t, q))(TARGETS, q0)
    return {"before": judged(q0), "experiment": judged(compensate(rb, a_exp, TARGETS, start=q0).q), "fast": judged(fast)}


@pytest.mark.slow
def test_delta_table_4_7_experiment(delta_study):
    """Figs 4.34, 4.41-4.42 from Table 4.7: the nacelle tilt the 20 mm longer rod causes (thesis 5.162
    deg; ours 5.169), the rotation left after compensation with the experimental model (5.056; ours
    5.051), its worst position error (9.322 mm; ours 10.50, 13 % above, not explained by the table's
    rounding) and the fast method's (13.4 mm; ours 13.98)."""
    assert abs(delta_study["before"][1] - 5.162) < 0.02
    assert abs(delta_study["experiment"][1] - 5.056) < 0.02
    assert 9.322 < delta_study["experiment"][0] < 1.15 * 9.322
    assert abs(delta_study["fast"][0] - 13.4) < 0.1 * 13.4
    assert delta_study["fast"][0] > delta_study["experiment"][0]


@pytest.mark.slow
def test_kiwibot_orientation_compensation_with_thesis_model():
    """§4.3, Figs 4.23-4.30: compensating orientation with the thesis' simulation-2 model (Table 4.5)
    cuts the largest nacelle rotation error of the nominal settings on the true robot by > 4x
    (thesis 0.535 -> 0.0518 deg) while the strut length stays within 1 mm and position errors stay
    millimetric (thesis 3.18 -> 3.92 mm)."""
    import jaxcal as jc

    rb = jc.robots.get("kiwibot")
    a_true = kb.thesis_perturbed(rb)
    q0 = jnp.asarray(kb.hemisphere_grid(40)[0])
    target = jax.vmap(kb.direct)(q0)
    strut = jnp.linalg.norm(target.p, axis=-1)
    a = np.array(a_true)
    for r in kb.TABLE_4_5:
        a[rb.index(r[0])] += r[4]
    q = jax.vmap(lambda R, s, x: least_squares(lambda y: kb.pointing_residual(jc.forward(rb, jnp.asarray(a), y), R, s), x))(
        target.R, strut, q0)

    def judged(q):
        pose = jc.forward(rb, a_true, q)
        angle = jnp.max(jnp.linalg.norm(jax.vmap(lambda R, Rt: log_so3(Rt.T @ R))(pose.R, target.R), axis=-1))
        drift = jnp.max(jnp.abs(jnp.linalg.norm(pose.p, axis=-1) - strut))
        return float(angle), float(drift), float(jnp.max(jnp.linalg.norm(pose.p - target.p, axis=-1)))

    (a0, _, _), (a1, drift, worst) = judged(q0), judged(q)
    assert a1 < a0 / 4 and drift < 1e-3 and worst < 5e-3, (a0, a1, drift, worst)
