"""Loop closure by continuation from a closed configuration (seed 004 §2.4, made robust).

The thesis closes the loops by Levenberg-Marquardt from a start (§2.4.1) and notes that the start
selects the assembly mode. A start far from the solution may converge to another assembly mode or
not at all, and nothing says which happened. Here the closure is solved by *continuation*: the
residual v(theta, t) is that of the mechanism with parameters and joint values moved along a path
from a reference where a closed configuration is known (t = 0: the nominal robot, the nominal
start) to the sample (t = 1),

    a(t) = a_ref + t (a - a_ref),   q(t) = q_ref + t (q - q_ref),

(the Delta moves what its sphere conditions read, `jaxcal.closure.delta._homotopy_path`: `track`'s `at`), and the
solution is followed along the path: an Euler predictor along the tangent
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

from jaxcal.linalg import solve_spd
from jaxcal.loops import varying_with

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


def path_jacobian(fn, x, c, dc):
    """(v, dv/dx, dv/dt) of fn(x, c) with c moving along dc = dc/dt, by forward mode in one pass: the pushforwards of
    (e_i, 0) and (0, dc), vmapped over the n + 1 directions, share the primal evaluation."""
    n = x.shape[0]
    ex = jnp.concatenate([jnp.eye(n, dtype=x.dtype), jnp.zeros((1, n), x.dtype)])
    ec = jax.tree_util.tree_map(lambda d: jnp.concatenate([jnp.zeros((n, *jnp.shape(d)), jnp.result_type(d)),
                                                           jnp.asarray(d)[None]]), dc)
    v, Vt = jax.vmap(lambda u, w: jax.jvp(fn, (x, c), (u, w)), out_axes=(None, -1))(ex, ec)
    return v, Vt[:, :-1], Vt[:, -1]


def _finite(x):
    return jnp.all(jnp.isfinite(x))


class _Settle(NamedTuple):
    """The state of `_settle`'s loop: the point p it evaluates next; the damped Newton's iterate th, |v| there, its
    damping mu, iterations kd and whether p is th's trial point; the corrector's iterate cy from its start cx, last
    correction size prev, |v| at cy, contraction kept, Newton iterations kc and step below round-off."""

    p: jnp.ndarray
    th: jnp.ndarray
    norm: jnp.ndarray
    mu: jnp.ndarray
    kd: jnp.ndarray
    at_trial: jnp.ndarray
    cx: jnp.ndarray
    cy: jnp.ndarray
    prev: jnp.ndarray
    cnorm: jnp.ndarray
    good: jnp.ndarray
    kc: jnp.ndarray
    still: jnp.ndarray
    V: jnp.ndarray
    dvdt: jnp.ndarray


def _settle(fn, c, dc, x, damped, tol, loose, active, max_steps: int = 100) -> _Settle:
    """From x, at a fixed point c of the path (`track`'s at(t)), `damped_newton`'s iterations (damped true; tolerance
    tol, at most max_steps) or `corrector`'s (tol, loose), in one loop that evaluates v and [V, dv/dt] of fn(., c)
    once a turn (a damped iteration takes two turns, at th and at its trial point): the residual's Jacobian is traced
    and compiled once for both. dv/dt is the derivative along dc = dc/dt (`path_jacobian`); dc None: not evaluated
    (kept 0), for a residual without a path. V and dvdt are kept at the accepted point (th; the corrector's last
    evaluated point), for the path's next tangent."""
    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    inf = jnp.asarray(jnp.inf, x.dtype)
    m = jax.eval_shape(fn, x, c).shape[0]

    def cond(s: _Settle):
        damping = s.at_trial | ((s.norm > 0.01 * tol) & (s.kd < max_steps) & (s.mu < 1e12))
        correcting = s.good & (s.cnorm > tol) & ~s.still & (s.kc <= CORRECTOR_STEPS)
        return active & jnp.where(damped, damping, correcting)

    def body(s: _Settle) -> _Settle:
        if dc is None:
            (v, V), dvdt = value_and_jacobian(lambda z: fn(z, c), s.p), s.dvdt
        else:
            v, V, dvdt = path_jacobian(fn, s.p, c, dc)
        norm_p = jnp.linalg.norm(v)
        delta = solve_spd(V.T @ V + jnp.where(damped, s.mu, 0.0) * eye, V.T @ v)
        # the damped Newton: at th, |v| there (first turn) and the trial point; at the trial, kept or not
        better = s.at_trial & jnp.isfinite(norm_p) & (norm_p < s.norm)
        th = jnp.where(better, s.p, s.th)
        norm = jnp.where(better | (~s.at_trial & (s.kd == 0)), norm_p, s.norm)
        mu = jnp.where(s.at_trial, jnp.where(better, jnp.maximum(s.mu * 0.1, 1e-15), s.mu * 10.0), s.mu)
        at_th = ~s.at_trial | better
        # the corrector (`corrector`'s rules)
        dx = -delta
        size = jnp.max(jnp.abs(dx))
        still = size <= 1e-13 * (1.0 + jnp.max(jnp.abs(s.cy)))
        contracts = (s.kc == 0) | (size <= CONTRACTION * s.prev) | still
        y_new = jnp.where(norm_p > tol, s.cy + dx, s.cy)  # a converged point is not moved
        good = (_finite(dx) & contracts & (jnp.max(jnp.abs(y_new - s.cx)) <= MAX_JUMP)) | (norm_p <= tol)
        cy = jnp.where(good, y_new, s.cy)
        damped_state = s._replace(p=jnp.where(s.at_trial, th, s.th - delta), th=th, norm=norm, mu=mu,
                                  kd=s.kd + s.at_trial, at_trial=~s.at_trial, V=jnp.where(at_th, V, s.V),
                                  dvdt=jnp.where(at_th, dvdt, s.dvdt))
        corrector_state = s._replace(p=cy, cy=cy, prev=size, cnorm=norm_p, good=good, kc=s.kc + (norm_p > tol),
                                     still=still & (norm_p <= loose), V=V, dvdt=dvdt)
        return jax.tree_util.tree_map(lambda d, c: jnp.where(damped, d, c), damped_state, corrector_state)

    init = _Settle(x, x, inf, jnp.asarray(1e-6, x.dtype), jnp.asarray(0), jnp.asarray(False), x, x, inf, inf,
                   jnp.asarray(True), jnp.asarray(0), jnp.asarray(False), jnp.zeros((m, x.shape[0]), x.dtype),
                   jnp.zeros(m, x.dtype))
    return jax.lax.while_loop(cond, body, varying_with(x, init))


def corrector(fn, x, tol, active=True, loose=None):
    """Newton (Gauss-Newton) corrector for fn(theta) = 0 from x: (x, converged, Newton steps taken).

    converged: |v| <= tol reached (or, for a least-squares closure whose minimum is not exactly 0,
    a step below round-off at |v| <= loose, default tol) while every step contracted
    (|dx_k| <= CONTRACTION |dx_(k-1)|, or below round-off) and the iterate stayed within MAX_JUMP of
    x. Stops after CORRECTOR_STEPS steps."""
    r = _settle(lambda z, _: fn(z), (), None, x, False, tol, tol if loose is None else loose, active)
    return r.cy, r.good & ((r.cnorm <= tol) | r.still), r.kc


def track(fn, x_init, tol, active=True, loose=None, at=None) -> Tracked:
    """Follow the root of fn(theta, at(t)) from t = 0 to t = 1 (see the module docstring).

    x_init: a start in the basin of the reference root at t = 0, polished there first by the damped Newton of
    `damped_newton` (tolerance 100 tol, at most 100 iterations). tol, loose: as in `corrector`. active: False skips
    all work. at: what the residual reads of the path parameter (a pytree; default t itself), computed with its
    derivative in t once per path step, outside the corrector's loop (`path_jacobian` then differentiates fn alone).

    The polish is the path loop's first turn, and it and the corrector of every later turn are one loop at the
    turn's fixed t, `_settle`, whose Jacobian [V, dv/dt] at the point it ends on gives the next tangent: the
    residual is traced and compiled once instead of four times (the polish's Jacobian and value, the tangent, the
    corrector). A corrector that ends by a step below round-off after its last evaluation (at |v| <= loose) leaves
    the tangent of the point that step started from, ~1e-13 away. The Delta's batch closure
    (`jaxcal.closure.delta.free_joints`, 125 settings): XLA compile 2.95-3.03 -> 2.10 s, at LLVM level 0 1.34 ->
    0.94-1.00 s; its continuation run at 1 cm errors 14.4 -> 12.4 ms; closed configurations as before to 3e-14 rad,
    every status and iteration count equal (docs/benchmarks.md, nineteenth session)."""
    loose = tol if loose is None else loose
    zero = jnp.zeros((), x_init.dtype)
    at = (lambda t: t) if at is None else at

    def cond(s):
        _, _, _, t, dt, k, _, ok0, first = s
        return (first & active) | (ok0 & (t < 1.0) & (dt >= MIN_DT) & (k < MAX_PATH_STEPS))

    def body(s):
        y, V, dvdt, t, dt, k, n, ok0, first = s
        d = -solve_spd(V.T @ V, V.T @ dvdt)  # the tangent at (y, t), eq 2.65
        t1 = jnp.where(first, zero, jnp.minimum(t + dt, 1.0))
        start = jnp.where(first, x_init, y + (t1 - t) * jnp.where(_finite(d), d, 0.0))
        c, dc = jax.jvp(at, (t1,), (jnp.ones_like(t1),))
        r = _settle(fn, c, dc, start, first, jnp.where(first, 100.0 * tol, tol), loose, active)
        # first turn: the path starts where the polish closes to loose
        x = jnp.where(_finite(r.th), r.th, x_init)
        polished = (x, r.V, r.dvdt, zero, jnp.ones_like(zero), k, r.kd, active & _finite(x) & (r.norm <= loose),
                    jnp.asarray(False))
        # later turns: the step is kept where the corrector converged, else halved
        ok = r.good & ((r.cnorm <= tol) | r.still)
        keep = lambda new, old: jnp.where(ok, new, old)  # noqa: E731
        stepped = (keep(r.cy, y), keep(r.V, V), keep(r.dvdt, dvdt), keep(t1, t),
                   keep(jnp.minimum(2.0 * dt, 1.0), 0.5 * dt), k + 1, n + r.kc, ok0, jnp.asarray(False))
        return jax.tree_util.tree_map(lambda a, b: jnp.where(first, a, b), polished, stepped)

    m = jax.eval_shape(lambda x, t: fn(x, at(t)), x_init, zero).shape[0]
    init = (x_init, jnp.zeros((m, x_init.shape[0]), x_init.dtype), jnp.zeros(m, x_init.dtype), zero, jnp.ones_like(zero),
            jnp.asarray(0), jnp.asarray(0), jnp.asarray(False), jnp.asarray(True))
    x, _, _, t, _, _, n, ok0, _ = jax.lax.while_loop(cond, body, varying_with(x_init, init))
    return Tracked(x, ok0 & (t >= 1.0), n, ok0)


def damped_newton(fn, start, tol, max_steps: int = 100, active=True):
    """Levenberg-Marquardt damped Newton on fn(theta) (no branch control): (theta, iterations).

    Each step solves (V^T V + mu I) d = -V^T v; a step that lowers |v| is kept and mu shrinks tenfold,
    otherwise mu grows tenfold. Stops at |v| <= tol / 100, after max_steps, or when mu exceeds 1e12."""
    r = _settle(lambda z, _: fn(z), (), None, start, True, tol, tol, active, max_steps)
    return jnp.where(_finite(r.th), r.th, start), r.kd


__all__ = ["CLOSED", "OTHER_MODE", "STATUS_NAMES", "Tracked", "UNCLOSED", "corrector", "damped_newton", "track"]
