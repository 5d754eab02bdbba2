"""Levenberg-Marquardt for the calibration core: the default solver ("lm") of `jaxcal.fit.core`.

Minimises |r(z)|^2 over z (the core's unknowns in typical-size units, so one damping for every unknown). Each
iteration takes the damped Gauss-Newton step (the identification solver of seed 004 §3 and of the nonlinear
methods surveyed in seed 000 §2; the update follows Madsen, Nielsen & Tingleff, "Methods for non-linear least
squares problems", 2004, §3.2)

    delta = argmin |r + J delta|^2 + lam |delta|^2,   the least-squares problem [J; sqrt(lam) I] solved by QR,

with geodesic acceleration (Transtrum & Sethna, "Improvements to the Levenberg-Marquardt algorithm for nonlinear
least-squares minimization", arXiv:1201.5885, 2012, §3): with v that damped step and r_vv the second derivative of
r along v, the second-order correction a = -(J^T J + lam I)^-1 J^T r_vv is added, the step taken being v + a / 2
when 2 |a| <= ACCEL_MAX |v|, else v. Transtrum & Sethna evaluate r_vv by a finite difference r(z + h v), one more
residual per iteration; here it is read off the last accepted step d instead (a secant, `secant_acceleration`):
r(z) - r(z - d) - J(z - d) d = r_dd / 2 + O(|d|^3), and r_vv = c^2 r_dd for v = c d, so the correction is used
when v is within ACCEL_COS of d's direction (along a valley the steps keep their direction), and only after the
first ACCEL_AFTER iterations, so that the short fits most calibrations are run exactly as without it. Along a curved
valley the step then follows the curve: on the Delta (seed 004 Table 4.6, 125 positions) the unbiased stages of a
noise-dominated fit crawled 200 steps unconverged (the cost down 2-5 %); accelerated they converge in tens of
steps, to the same cost. No residual evaluation is added to the compiled loop: the finite-difference form cost
~0.5 s more XLA compile per fit (Stanford arm, 200 positions: first call 3.7 s against 3.1 s).
The gain ratio rho = (|r|^2 - |r(z + delta)|^2) / (|r|^2 - |r + J v|^2) decides: rho >= ACCEPT keeps the step and
lowers the damping, lam <- lam max(1/3, 1 - (2 rho - 1)^3), nu <- 2; otherwise
lam <- lam nu, nu <- 2 nu (Nielsen's update, eq 3.16 there). The start is lam = TAU max diag(J^T J).

It stops (converged) after an accepted step that changes every z_i by at most atol + rtol |z_i| and every
residual r_i by at most atol + rtol |r_i| (such a step is accepted when the cost rises by no more than round-off,
`ROUND_OFF`), or after a step whose predicted decrease |r|^2 - |r + J v|^2 is at most ROUND_OFF |r|^2 (the linear
model sees nothing left to gain): right after an accepted step, such a step within the step tolerances is not
evaluated and z is returned as it is (the iteration counts as a step); otherwise the step is evaluated and accepted
when the cost rises by no more than round-off. A run given a relative decrease `stop` > 0 (a start, which the next
fit refits: `jaxcal.fit.core.START_STOP`; a calibration's fit, at Bates and Watts' relative offset:
`jaxcal.fit.core.offset_stop`) also stops, converged, at a step whose predicted decrease is at most
stop |r|^2 while the damping is at most its start value (no rejection has raised it since), z returned as it is
without evaluating the step. Else it stops after max_steps iterations (accepted and
rejected) unconverged.
Why not optimistix's LM, which the core used before: the same iteration compiled ~1.6x faster here (XLA, 2-core
CPU: 3.7 s vs 5.9 s for the Stanford arm, 200 positions; 5.0 vs 7.0 s for poses), and compile time is most of
a first calibration and of the test suite. The residual and its Jacobian come from one forward-mode pass, or from
the caller's `jac` (the core passes its reverse-mode data Jacobian: `jaxcal.fit.core.data_residual_and_jacobian`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxcal.loops import varying_with

ACCEPT = 1e-3  # smallest gain ratio of an accepted step
# Initial damping relative to the largest diagonal entry of J^T J. Madsen et al. (§3.2) advise 1e-6 when the start
# is believed close to the solution, 1e-3 otherwise; the core starts from the nominal robot with the device frames
# fitted, within millimetres of the optimum: there the Gauss-Newton step is good, and a larger start damping only
# holds back the weak directions for the steps it takes to decay (at most 1/3 a step). LM steps of a whole `identify`
# (docs/benchmarks.md, twelfth session), 1e-6 -> 1e-9 with the round-off stop of `advance`: Stanford arm, 200
# positions 9 -> 6, poses 11 -> 7; UR10 47 -> 34; planar four-bar 337 -> 215; Delta 252 -> 197; TALOS 90 -> 96 (its
# bias stages); the same RMS. Without that stop 1e-9 and 1e-10 took the fewest steps over 8 cases, 1e-12 more.
TAU = 1e-9
# Relative cost change taken as round-off (a sum of ~1e3 squares in float64 carries ~1e-13 of relative error).
ROUND_OFF = 1e-10
LAM_MAX = 1e30  # damping past which no step can change anything: stop, unconverged
ACCEL_COS = 0.9  # the acceleration is used only when the step v is within this cosine of the last accepted step
ACCEL_MAX = 0.75  # the acceleration a is used only when 2 |a| <= ACCEL_MAX |v| (Transtrum & Sethna's alpha)
# Iterations before the acceleration is used: the fits it shortens are long (the Delta's 200-step crawls); the short
# ones (the Stanford arm's 3 + 3 steps) run exactly as plain LM.
ACCEL_AFTER = 8


class LMResult(NamedTuple):
    """z: the estimate; converged; steps: iterations taken (accepted and rejected); cost: |r(z)|^2; history: |r|^2
    at z0 and after each iteration (a rejected step repeats the cost), NaN past the last, shape (max_steps + 1,);
    r, J: the residual and its Jacobian at z (with a step limit of 0: at z0, the core's evaluation of J)."""

    z: jnp.ndarray
    converged: jnp.ndarray
    steps: jnp.ndarray
    cost: jnp.ndarray
    history: jnp.ndarray
    r: jnp.ndarray
    J: jnp.ndarray


def residual_and_jacobian(fn: Callable, z, args):
    """(r, J) = (fn(z, args), dr/dz): the pushforwards of the unit vectors, vmapped, share one primal pass."""
    r, J = jax.vmap(lambda e: jax.jvp(lambda u: fn(u, args), (z,), (e,)), out_axes=(None, -1))(jnp.eye(z.shape[0], dtype=z.dtype))
    return r, J


def damped_factor(J, r, lam, data_rows: int | None = None):
    """(U, delta): U upper triangular with U^T U = J^T J + lam I, and delta minimising |r + J delta|^2 + lam |delta|^2
    (the least-squares problem [J; sqrt(lam) I] delta = [-r; 0]).

    Two triangular factorisations, no orthogonal factor formed: R of [J r] gives R1 and c = Q1^T r (J = Q1 R1),
    then R of [[R1, c], [sqrt(lam) I, 0]] gives the damped system in triangular form (MINPACK's way of solving
    the damped step from the QR of J; 0.29 ms instead of 0.46 ms for a 704 x 52 J, forming Q).

    data_rows (static): the rows from this one on have at most one non-zero entry each (the core's prior rows,
    `jaxcal.fit.core.prior_rows`). All such rows of column j, with the damping, add (a_j delta_j + b_j)^2 to the
    problem up to a constant, a_j^2 = lam + sum_k J_kj^2 and a_j b_j = sum_k J_kj r_k: they take the damping rows'
    place as [diag(a), b], and the first factorisation runs on the data rows alone (the Delta, 384 data rows and
    332 prior rows, 88 columns: 1.01-1.06 -> 0.83-0.85 ms)."""
    n = J.shape[1]
    if data_rows is None:
        a, b = jnp.full(n, jnp.sqrt(lam), J.dtype), jnp.zeros(n, J.dtype)
    else:
        Jp, rp, J, r = J[data_rows:], r[data_rows:], J[:data_rows], r[:data_rows]
        a = jnp.sqrt(lam + jnp.sum(Jp**2, axis=0))
        b = (Jp.T @ rp) / jnp.where(a > 0, a, 1.0)  # a = 0 (lam 0, no such row): the column's sum is 0 too
    R = jnp.linalg.qr(jnp.concatenate([J, r[:, None]], axis=1), mode="r")[:n]
    R2 = jnp.linalg.qr(jnp.concatenate([R, jnp.concatenate([jnp.diag(a), b[:, None]], axis=1)]), mode="r")
    return R2[:n, :n], jax.scipy.linalg.solve_triangular(R2[:n, :n], -R2[:n, n], lower=False)


def damped_step(J, r, lam):
    """delta minimising |r + J delta|^2 + lam |delta|^2 (`damped_factor`)."""
    return damped_factor(J, r, lam)[1]


def secant_acceleration(J, U, v, last, bend):
    """The second-order correction a = -(U^T U)^-1 J^T r_vv of the damped step v (module docstring), with r_vv read
    off the last accepted step `last`: bend = r(z) - r(z_prev) - J(z_prev) last = r_ll / 2 + O(|last|^3), so for v
    along last (v = c last), r_vv = c^2 r_ll = 2 c^2 bend. 0 unless v is within ACCEL_COS of last's direction, a is
    finite and 2 |a| <= ACCEL_MAX |v| (the step is then v alone)."""
    ll = last @ last
    c = (v @ last) / jnp.where(ll > 0, ll, 1.0)
    aligned = (ll > 0) & (jnp.abs(v @ last) >= ACCEL_COS * jnp.linalg.norm(v) * jnp.sqrt(ll))
    rvv = 2.0 * c**2 * bend
    a = -jax.scipy.linalg.solve_triangular(U, jax.scipy.linalg.solve_triangular(U.T, J.T @ rvv, lower=True), lower=False)
    use = aligned & jnp.all(jnp.isfinite(a)) & (2.0 * jnp.linalg.norm(a) <= ACCEL_MAX * jnp.linalg.norm(v))
    return jnp.where(use, a, 0.0)


class LMState(NamedTuple):
    """The iteration's state: the current (accepted) point z with its residual r and Jacobian J, the damping
    lam and its growth factor nu, iterations taken, and whether the last step met the stopping test."""

    z: jnp.ndarray
    r: jnp.ndarray
    J: jnp.ndarray
    lam: jnp.ndarray
    nu: jnp.ndarray
    steps: jnp.ndarray
    converged: jnp.ndarray
    last: jnp.ndarray  # the last accepted step (0 before the first)
    bend: jnp.ndarray  # r(z) - r(z_prev) - J(z_prev) last: half the second derivative of r along last
    lam0: jnp.ndarray  # the damping at the start (`initial_damping` there)
    cost: jnp.ndarray  # |r|^2 at z, kept from the step that computed it: each sum over the rows is a few kernels of its own


def initial_damping(J):
    """lam = TAU max diag(J^T J) (TAU when J is 0)."""
    lam0 = TAU * jnp.max(jnp.sum(J**2, axis=0))
    return jnp.where(lam0 > 0, lam0, TAU)


def init(fn: Callable, z0, args, jac: Callable | None = None) -> LMState:
    """The state at z0 (damping `initial_damping`). jac(z, args) -> (r, J): how to evaluate the residual and its
    Jacobian together (default `residual_and_jacobian` of fn)."""
    r0, J0 = (jac or functools.partial(residual_and_jacobian, fn))(z0, args)
    lam0 = initial_damping(J0)
    return LMState(z0, r0, J0, lam0, jnp.asarray(2.0, z0.dtype), jnp.asarray(0), jnp.asarray(False),
                   jnp.zeros_like(z0), jnp.zeros_like(r0), lam0, r0 @ r0)


def step(fn: Callable, s: LMState, args, rtol: float, atol: float, jac: Callable | None = None) -> LMState:
    """One iteration: the damped step with its geodesic acceleration, kept or not by its gain ratio, the damping
    updated (module docstring)."""
    return advance(jac or functools.partial(residual_and_jacobian, fn), s, args, rtol, atol, jnp.asarray(False))


def step_columns(free, width: int):
    """(idx (width,), valid (width,)): the unknowns a step moves (free > 0) first, in index order, then the others
    as padding (valid False). The damped step is solved on J[:, idx] * valid only: the factorisation's cost grows
    with the square of its columns, and a closed mechanism estimates few of many (the Delta: 46 of 166, its QR of
    707 x 167 2.2 ms against 0.3 ms for 47 columns)."""
    idx = jnp.argsort(free <= 0, stable=True)[:width]
    return idx, free[idx] > 0


def advance(rj: Callable, s: LMState, args, rtol: float, atol: float, first, free=None, width: int | None = None,
            data_rows: int | None = None, stop=0.0) -> LMState:
    """`step` with the residual-and-Jacobian function rj; when `first` is true the step is 0 and
    the point is taken as it is (the state then holds r and J at z and lam = `initial_damping`, as `init` gives, and
    counts no step). `least_squares` starts its loop with such a step, so rj appears once in the compiled loop, not
    also before it: the Jacobian is most of what XLA compiles. free: 0/1 per unknown, the columns of J the step
    uses (None: all); the state keeps every column. width (static, with free): the step is solved on that many
    columns (`step_columns`; at least the number of free unknowns), not on all of J's with the others zeroed.
    data_rows (static): where the rows of one non-zero entry each begin (`damped_factor`; None: no such rows).
    stop (traced): a step predicted to lower the cost by at most stop |r|^2, the damping at most its start value and
    just lowered, ends the run at z, unevaluated (0: never)."""
    if free is not None and width is not None:  # the step's unknowns gathered, the step spread back
        idx, valid = step_columns(free, width)
        take = lambda J: J[:, idx] * valid  # noqa: E731
        spread = lambda d: jnp.zeros_like(s.z).at[idx].set(jnp.where(valid, d, 0.0))  # noqa: E731
        last = s.last[idx]
    else:  # every column, the held ones zeroed
        take = (lambda J: J) if free is None else (lambda J: J * free)  # noqa: E731
        spread = lambda d: d  # noqa: E731
        last = s.last
    J = take(s.J)

    def proposal(_):  # the damped step v and the step taken, v plus half the acceleration
        U, v = damped_factor(J, s.r, s.lam, data_rows)
        return v, v + 0.5 * jnp.where(s.steps >= ACCEL_AFTER, secant_acceleration(J, U, v, last, s.bend), 0.0)

    # the first turn only evaluates the start: its state holds no Jacobian to factor yet (0.4 ms of QR on the
    # Stanford arm's 704 x 52 zeros, 2 ms on the Delta's 707 x 166, in every solve and every Jacobian read)
    v, step_taken = jax.lax.cond(first, lambda _: (jnp.zeros_like(last), jnp.zeros_like(last)), proposal, None)
    delta = spread(step_taken)
    z_new = s.z + delta
    cost = s.cost
    predicted = cost - jnp.sum((s.r + J @ v) ** 2)
    # the linear model predicts no decrease beyond round-off: z is optimal to working precision. A step of an
    # ill-conditioned fit there moves the residuals by round-off amplified ~cond(J), which can exceed the residual
    # tolerance while the cost does not change (Stanford arm seen from 4 m, far frame and robot estimated together:
    # 6 rejections in a row, the damping x 2^21, before a step shrank below the tolerances)
    negligible = ~first & (predicted <= ROUND_OFF * cost)
    # after an accepted step (nu = 2: the damping was just lowered, not raised by rejections) such a step within the
    # step tolerances ends the run at z without being evaluated, the residual and Jacobian being most of an iteration
    # (Stanford arm, 200 poses: the frames-only fit's third step, predicted decrease 1e-15 of the cost, 1.9e-8 in z)
    # a run given `stop` (a start; a fit at its relative offset) ends at a step that would gain less, not evaluated.
    # Only while the damping is at most its start value (kept in the state, no pass over J) and was just lowered
    # (nu = 2): a step held back by damping that rejections raised predicts a small decrease far from the optimum too
    enough = ~first & (stop > 0) & (predicted <= stop * cost) & (s.nu <= 2.0) & (s.lam <= s.lam0)
    unevaluated = (negligible & (s.nu <= 2.0) & jnp.all(jnp.abs(delta) <= atol + rtol * jnp.abs(z_new))) | enough
    r_new, J_new = jax.lax.cond(unevaluated, lambda: (s.r, s.J), lambda: rj(z_new, args))
    z_new = jnp.where(unevaluated, s.z, z_new)
    cost_new = r_new @ r_new
    actual = cost - cost_new
    small = (jnp.all(jnp.abs(delta) <= atol + rtol * jnp.abs(z_new))
             & jnp.all(jnp.abs(r_new - s.r) <= atol + rtol * jnp.abs(r_new)))
    final = small | negligible | enough
    # a step below the tolerances, or of negligible predicted gain, that leaves the cost unchanged to round-off ends
    # the run: there the gain ratio is a ratio of round-off errors, and rejecting on it only grows lam until some
    # step happens to pass
    at_round_off = final & (actual >= -ROUND_OFF * cost)
    accepted = first | (jnp.isfinite(cost_new) & (((actual >= 0) & (actual >= ACCEPT * predicted)) | at_round_off))
    rho = actual / jnp.where(predicted > 0, predicted, 1.0)
    keep = lambda new, old: jnp.where(accepted, new, old)  # noqa: E731
    lam = jnp.where(accepted, s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), s.lam * s.nu)
    moved = accepted & ~first & ~unevaluated
    # the start's damping only on the first turn: under jnp.where both sides ran, gathering and squaring the step's
    # columns of every later turn's Jacobian too (the Delta: 716 x 88 entries a step)
    lam = jax.lax.cond(first, lambda: initial_damping(take(J_new)), lambda: lam)
    return LMState(keep(z_new, s.z), keep(r_new, s.r), keep(J_new, s.J), lam,
                   jnp.where(accepted, 2.0, 2.0 * s.nu), s.steps + jnp.where(first, 0, 1), ~first & accepted & final,
                   jnp.where(moved, delta, s.last), jnp.where(moved, r_new - s.r - J @ step_taken, s.bend),
                   jnp.where(first, lam, s.lam0), keep(cost_new, s.cost))


def starting_with(rj: Callable, start, first) -> Callable:
    """rj, but on the loop's first turn (`advance`'s first, which evaluates z0) with start = (r0, J0, given) and given
    true: (r0, J0), the residual and Jacobian at z0 that the caller already has (a solve that begins where the last
    one, or a Jacobian read, ended), instead of evaluating them again."""
    r0, J0, given = start
    return lambda z, args: jax.lax.cond(first & given, lambda: (r0, J0), lambda: rj(z, args))


def least_squares(fn: Callable, z0, args, *, max_steps: int, rtol: float, atol: float,
                  jac: Callable | None = None, limit=None, free=None, width: int | None = None, start=None,
                  data_rows: int | None = None, stop=0.0) -> LMResult:
    """Minimise |fn(z, args)|^2 from z0 by Levenberg-Marquardt (see the module docstring); jac as in `init`.
    The loop's first turn evaluates r and J at z0 (`advance` with first=True). limit: a traced cap on the
    iterations below max_steps (max_steps sizes the history, so it is static); 0 returns r and J at z0, which is
    how the core evaluates its Jacobian with the solver's executable instead of compiling the Jacobian again.
    free: 0/1 per unknown (traced): only those move, the others' columns of J are left out of every step (None:
    all move); the returned J has every column, so that a caller who fits some unknowns gets the Jacobian of all
    at the solution without evaluating it again. width: `advance`'s (static). start: (r0, J0, given) with given
    (traced) true: r and J at z0, not evaluated again (`starting_with`). data_rows: `advance`'s (static). stop:
    `advance`'s (traced; 0: the run ends only by the tolerances, round-off or the step limit)."""
    cap = max_steps if limit is None else jnp.minimum(max_steps, limit)
    rj = jac or functools.partial(residual_and_jacobian, fn)
    r_shape, J_shape = jax.eval_shape(rj, z0, args)
    blank = LMState(z0, jnp.zeros(r_shape.shape, r_shape.dtype), jnp.zeros(J_shape.shape, J_shape.dtype),
                    jnp.asarray(1.0, z0.dtype), jnp.asarray(2.0, z0.dtype), jnp.asarray(0), jnp.asarray(False),
                    jnp.zeros_like(z0), jnp.zeros(r_shape.shape, r_shape.dtype), jnp.asarray(1.0, z0.dtype),
                    jnp.asarray(0.0, z0.dtype))

    def body(carry):
        s, hist, first = carry
        s = advance(rj if start is None else starting_with(rj, start, first), s, args, rtol, atol, first, free, width,
                    data_rows, stop)
        return s, hist.at[s.steps].set(s.cost), jnp.asarray(False)

    s, hist, _ = jax.lax.while_loop(lambda c: c[2] | (~c[0].converged & (c[0].steps < cap) & (c[0].lam < LAM_MAX)),
                                    body, varying_with(z0, (blank, jnp.full(max_steps + 1, jnp.nan, z0.dtype),
                                                            jnp.asarray(True))))
    return LMResult(s.z, s.converged, s.steps, s.cost, hist, s.r, s.J)


@dataclasses.dataclass(frozen=True)
class LevenbergMarquardt:
    """This module's solver with its tolerances (hashable: it selects the compiled solver)."""

    rtol: float
    atol: float

    def __call__(self, fn: Callable, z0, args, max_steps: int, jac: Callable | None = None, limit=None, free=None,
                 width: int | None = None, start=None, data_rows: int | None = None, stop=0.0) -> LMResult:
        return least_squares(fn, z0, args, max_steps=max_steps, rtol=self.rtol, atol=self.atol, jac=jac, limit=limit,
                             free=free, width=width, start=start, data_rows=data_rows, stop=stop)


__all__ = ["LMResult", "LMState", "LevenbergMarquardt", "damped_factor", "damped_step", "secant_acceleration",
           "init", "initial_damping", "least_squares", "residual_and_jacobian", "starting_with", "step", "step_columns", "advance"]
