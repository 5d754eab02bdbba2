"""Loop closure by continuation from a closed configuration (seed 004 §2.4, made robust).

The thesis closes the loops by Levenberg-Marquardt from a start (§2.4.1) and notes that the start
selects the assembly mode. A start far from the solution may converge to another assembly mode or
not at all, and nothing says which happened. Here the closure is solved by *continuation*: the
residual v(theta, t) is that of the mechanism with parameters and joint values moved along a path
from a reference where a closed configuration is known (t = 0: the nominal robot, the nominal
start) to the sample (t = 1),

    a(t) = a_ref + t (a - a_ref),   q(t) = q_ref + t (q - q_ref),

and the solution is followed along the path: an Euler predictor along the tangent
d theta / dt = -(V^T V)^-1 V^T dv/dt (V = dv/dtheta, the implicit function theorem of eq 2.65),
then a Gauss-Newton corrector. A step is accepted only when the corrector contracts (each Newton
correction at most CONTRACTION times the previous one: the iterates stay in the basin of the root
the predictor aimed at, Deuflhard's affine-invariant test) and converges; otherwise the step is
halved. The first step tries the whole path at once (dt = 1), so a sample near the reference costs
one predictor and a few Newton iterations. A solution reached this way lies on the branch
continuously connected to the reference configuration: the assembly mode cannot switch silently.

Every loop here takes an `active` flag: under `vmap` a `while_loop` runs until its slowest element
is done, so a batch in which no element is active costs no iteration (the fast paths use this to
fall back per sample at no cost to the samples they close).

Status per sample (`status`): CLOSED (on the reference branch), UNCLOSED (no closed configuration
found), OTHER_MODE (a direct solve from the start closes, but not on the branch continued from the
reference: another assembly mode, or a configuration the path cannot reach without crossing a
singularity). Only CLOSED counts as closed.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.linalg import solve_small

CLOSED, UNCLOSED, OTHER_MODE = 0, 1, 2
STATUS_NAMES = {CLOSED: "closed", UNCLOSED: "unclosed", OTHER_MODE: "other assembly mode"}
CONTRACTION = 0.5  # a corrector step longer than this share of the previous one rejects the path step
CORRECTOR_STEPS = 8  # Newton iterations per path step at most
MAX_PATH_STEPS = 60  # predictor-corrector steps at most (accepted and rejected)
MIN_DT = 2.0**-12  # path step below which the continuation gives up
MAX_JUMP = 0.5  # largest corrector move (rad or m, max norm) from the predicted point


class Tracked(NamedTuple):
    """Result of `track`: free joints, whether t = 1 was reached, Newton iterations spent, and whether
    the reference (t = 0) closed."""

    theta: jnp.ndarray
    reached: jnp.ndarray
    steps: jnp.ndarray
    ref_ok: jnp.ndarray


def value_and_jacobian(fn, x):
    """(v, V) = (fn(x), dv/dx) by forward mode in one pass: the pushforwards of the unit vectors, vmapped, share
    the primal evaluation (jacfwd with the value as auxiliary output traces fn twice, doubling what XLA compiles)."""
    v, V = jax.vmap(lambda e: jax.jvp(fn, (x,), (e,)), out_axes=(None, -1))(jnp.eye(x.shape[0], dtype=x.dtype))
    return v, V


def _newton_step(fn, x):
    """(dx, |v|) of one Gauss-Newton step dx = -(V^T V)^-1 V^T v for the residual fn at x."""
    v, V = value_and_jacobian(fn, x)
    dx = -solve_small(V.T @ V, V.T @ v)
    return dx, jnp.linalg.norm(v)


def _finite(x):
    return jnp.all(jnp.isfinite(x))


def corrector(fn, x, tol, active=True, loose=None):
    """Newton (Gauss-Newton) corrector for fn(theta) = 0 from x: (x, converged, Newton steps taken).

    converged: |v| <= tol reached (or, for a least-squares closure whose minimum is not exactly 0,
    a step below round-off at |v| <= loose, default tol) while every step contracted
    (|dx_k| <= CONTRACTION |dx_(k-1)|, or below round-off) and the iterate stayed within MAX_JUMP of
    x. Stops after CORRECTOR_STEPS steps."""
    loose = tol if loose is None else loose

    def cond(s):
        _, _, norm, good, k, still = s
        return active & good & (norm > tol) & ~still & (k <= CORRECTOR_STEPS)

    def body(s):
        y, prev, _, _, k, _ = s
        dx, norm = _newton_step(fn, y)
        size = jnp.max(jnp.abs(dx))
        still = size <= 1e-13 * (1.0 + jnp.max(jnp.abs(y)))
        contracts = (k == 0) | (size <= CONTRACTION * prev) | still
        y_new = jnp.where(norm > tol, y + dx, y)  # a converged point is not moved
        good = (_finite(dx) & contracts & (jnp.max(jnp.abs(y_new - x)) <= MAX_JUMP)) | (norm <= tol)
        return jnp.where(good, y_new, y), size, norm, good, k + (norm > tol), still & (norm <= loose)

    init = (x, jnp.inf, jnp.inf, jnp.asarray(True), 0, jnp.asarray(False))
    y, _, norm, good, k, still = jax.lax.while_loop(cond, body, init)
    return y, good & ((norm <= tol) | still), k


def _tangent(fn_t, x, t):
    """d theta / dt = -(V^T V)^-1 V^T dv/dt at (x, t) (implicit function theorem, eq 2.65)."""
    _, Vt = value_and_jacobian(lambda zt: fn_t(zt[:-1], zt[-1]), jnp.append(x, t))  # [V, dv/dt] in one pass
    V, dvdt = Vt[:, :-1], Vt[:, -1]
    d = -solve_small(V.T @ V, V.T @ dvdt)
    return jnp.where(_finite(d), d, 0.0)


def track(fn_t, x_init, tol, active=True, loose=None) -> Tracked:
    """Follow the root of fn_t(theta, t) from t = 0 to t = 1 (see the module docstring).

    x_init: a start in the basin of the reference root at t = 0, polished there by `damped_newton`
    first. tol, loose: as in `corrector`. active: False skips all work."""
    t0 = jnp.zeros((), x_init.dtype)
    fn0 = lambda z: fn_t(z, t0)  # noqa: E731
    x, k0, norm0 = _damped(fn0, x_init, 100.0 * tol, 100, active)
    ok0 = active & _finite(x) & (norm0 <= (tol if loose is None else loose))

    def cond(s):
        _, t, dt, k, _ = s
        return active & ok0 & (t < 1.0) & (dt >= MIN_DT) & (k < MAX_PATH_STEPS)

    def body(s):
        y, t, dt, k, n = s
        t1 = jnp.minimum(t + dt, 1.0)
        pred = y + (t1 - t) * _tangent(fn_t, y, t)
        y1, ok, kc = corrector(lambda z: fn_t(z, t1), pred, tol, loose=loose)
        return (jnp.where(ok, y1, y), jnp.where(ok, t1, t), jnp.where(ok, jnp.minimum(2.0 * dt, 1.0), 0.5 * dt),
                k + 1, n + kc)

    x, t, _, _, n = jax.lax.while_loop(cond, body, (x, t0, jnp.ones_like(t0), 0, k0))
    return Tracked(x, active & ok0 & (t >= 1.0), n, ok0)


def damped_newton(fn, start, tol, max_steps: int = 100, active=True):
    """Levenberg-Marquardt damped Newton on fn(theta) (no branch control): (theta, iterations).

    Each step solves (V^T V + mu I) d = -V^T v; a step that lowers |v| is kept and mu shrinks tenfold,
    otherwise mu grows tenfold. Stops at |v| <= tol / 100, after max_steps, or when mu exceeds 1e12."""
    th, k, _ = _damped(fn, start, tol, max_steps, active)
    return th, k


def _damped(fn, start, tol, max_steps, active):
    """`damped_newton`, also returning |v| at the result (inf when inactive)."""
    eye = jnp.eye(start.shape[0], dtype=start.dtype)

    def cond(s):
        _, norm, mu, k = s
        return active & (norm > 0.01 * tol) & (k < max_steps) & (mu < 1e12)

    def body(s):
        th, norm, mu, k = s
        v, V = value_and_jacobian(fn, th)
        norm = jnp.where(k == 0, jnp.linalg.norm(v), norm)
        trial = th - solve_small(V.T @ V + mu * eye, V.T @ v)
        trial_norm = jnp.linalg.norm(fn(trial))
        better = jnp.isfinite(trial_norm) & (trial_norm < norm)
        return (jnp.where(better, trial, th), jnp.where(better, trial_norm, norm),
                jnp.where(better, jnp.maximum(mu * 0.1, 1e-15), mu * 10.0), k + 1)

    th, norm, _, k = jax.lax.while_loop(cond, body, (start, jnp.asarray(jnp.inf, start.dtype), jnp.asarray(1e-6), 0))
    return jnp.where(_finite(th), th, start), k, norm


__all__ = ["CLOSED", "OTHER_MODE", "STATUS_NAMES", "Tracked", "UNCLOSED", "corrector", "damped_newton", "track"]
