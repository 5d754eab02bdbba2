"""Identifiable (base) parameters per calibration method and observability indices.

seed 001 Appendix III: the observation matrix W of a method (autodiff Jacobian of its residual
at generated points) is QR-decomposed with its columns in priority order; the base set is the
first independent columns (|R_ii| > tau max|R_jj|; eq 34 sets tau = c eps, with c the number of columns, and
`PIVOT_TOL` here is wider: see there), zero columns have no effect
and the others are regrouped, W_r = W_b beta with beta = R1^-1 R2 (eq 37). The unknown plane
coefficients of plane1_unknown / plane2_unknown are identified with the robot (ordered first,
as in eq 15) but not counted.

Observability indices of W_b with singular values s_1 >= ... >= s_b (m rows):
Menq-Borm O1 = (s_1 ... s_b)^(1/b) / sqrt(m), minimum singular value s_b, condition number
s_1 / s_b, noise amplification index s_b^2 / s_1.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit.base import BaseSet, base_set, regrouping_relations
from jaxcal.fit.methods import PLANE_METHODS, check_method, extra_names, generate_points, n_rows, observation_matrix
from jaxcal.kin.model import Robot

EXTRA_PRIORITY = 10.0  # plane coefficients come first (eq 15 column order)
# The numerical zero of the QR pivots, relative to the largest. Seed 001's eq 34 takes c eps with c the number of columns
# (9.6e-15 for Table 2's W); the pivots of columns dependent by structure land at round-off, which that rule can miss:
# the largest such pivot was 9.0e-15 (plane2_known j6.r, Table 2's priorities, 40 points, seed 0), and evaluating the
# same points from one trace instead of two moved it across (docs/identifiability.md). The pivots of the columns kept
# are 9e-3 or more (Stanford, nine methods; MRR-1, two; seeds 0 and 1), so any threshold in between gives the seed's
# table; 1e-10 (the core's base-set rule, `jaxcal.fit.core.BASE_TOL`) sits well inside that gap. c= gives eq 34's.
PIVOT_TOL = 1e-10


@dataclasses.dataclass(frozen=True)
class Identifiable:
    """Base parameters of one method: `count` robot parameters `names`, `regroup` relations."""

    method: str
    count: int
    names: tuple[str, ...]
    regroup: tuple[str, ...]
    no_effect: tuple[str, ...]
    regrouped: tuple[str, ...]
    extra: tuple[str, ...]  # identified method unknowns (plane coefficients), not in count
    condition: float
    indices: dict
    basis: BaseSet
    W: np.ndarray
    all_names: tuple[str, ...]
    constraint: float
    seconds: float

    def status(self, name: str) -> str:
        """'b' (base), 'n' (regrouped), '0' (no effect) or '-' (not identified: priority 0)."""
        if name in self.names or name in self.extra:
            return "b"
        if name in self.regrouped:
            return "n"
        return "0" if name in self.no_effect else "-"


def observability_indices(Wb) -> dict:
    """Observability indices of Sun & Hollerbach (2008) from the singular values s_1 >= ... >= s_b of the
    m x b matrix Wb: "O1" Menq-Borm (s_1 ... s_b)^(1/b) / sqrt(m), "O2" inverse condition s_b / s_1, "O3" minimum
    singular value s_b, "O4" noise amplification s_b^2 / s_1, "O5" 1 / sum_i 1/s_i; also under the names
    menq_borm, condition (s_1 / s_b), min_singular and noise_amplification."""
    Wb = np.asarray(Wb, float)
    s = np.linalg.svd(Wb, compute_uv=False)
    m, b = Wb.shape
    named = {
        "menq_borm": float(np.exp(np.mean(np.log(s))) / np.sqrt(m)),
        "min_singular": float(s[-1]),
        "condition": float(s[0] / s[-1]),
        "noise_amplification": float(s[-1] ** 2 / s[0]),
    }
    return dict(named, O1=named["menq_borm"], O2=float(s[-1] / s[0]), O3=named["min_singular"],
                O4=named["noise_amplification"], O5=float(1.0 / np.sum(1.0 / s)))


def _priority(robot: Robot, priority, include_gains):
    p = np.asarray(robot.priority if priority is None else priority, float).copy()
    if isinstance(priority, dict):
        raise TypeError("priority must be an array over robot.names")
    if p.shape != (robot.n_params,):
        raise ValueError(f"priority must have one entry per robot parameter ({robot.n_params}), got shape {p.shape}")
    if not include_gains:
        p[np.array([u == "gain" for u in robot.units])] = 0.0
    return p


def identifiable_from_W(robot: Robot, method: str, W, priority=None, include_gains=True, c=None,
                        constraint=0.0, seconds=0.0) -> Identifiable:
    """Base set of an observation matrix W (columns: robot parameters, then the method's unknowns)."""
    extras = extra_names(method)
    nr = robot.n_params
    W = np.asarray(W)[:, : nr + len(extras)]
    p = np.concatenate([_priority(robot, priority, include_gains), np.full(len(extras), EXTRA_PRIORITY)])
    names = tuple(robot.names) + extras
    bs = base_set(W, p, PIVOT_TOL / np.finfo(float).eps if c is None else c)
    robot_base = [i for i in bs.independent if i < nr]
    wb = W[:, bs.independent]
    return Identifiable(
        method=method, count=len(robot_base), names=tuple(names[i] for i in robot_base),
        regroup=tuple(regrouping_relations(bs, names)),
        no_effect=tuple(names[i] for i in bs.no_effect), regrouped=tuple(names[i] for i in bs.regrouped),
        extra=tuple(names[i] for i in bs.independent if i >= nr), condition=float(np.linalg.cond(wb)),
        indices=observability_indices(wb), basis=bs, W=W, all_names=names, constraint=constraint, seconds=seconds,
    )


def identifiable(robot: Robot, method: str, n_configs: int = 60, seed: int = 0, priority=None,
                 include_gains: bool = True, a=None, plane=None, c: float | None = None) -> Identifiable:
    """Identifiable parameters of `robot` for a GECARO calibration method (seed 001 App. III).

    n_configs samples (configurations, or pairs for link/plane2/distance methods) are generated
    at parameters a (default nominal) satisfying the method's constraint; priority: one number
    per robot parameter (higher first, 0 = not identified; default robot.priority, GECARO §4);
    include_gains=False gives the gains priority 0. For one-equation methods n_configs is raised so
    that W has at least twice as many rows as columns. c: the pivot threshold is c eps max|R_jj| (eq 34 with c =
    the number of columns); default PIVOT_TOL max|R_jj|."""
    check_method(method)
    t0 = time.perf_counter()
    a = robot.nominal if a is None else jnp.asarray(a, dtype=jnp.float64)
    n = max(n_configs, -(-2 * (robot.n_params + 3) // n_rows(method)))  # W must be tall (rows >= 2 columns)
    pts = generate_points(robot, method, n, seed=seed, a=a, plane=plane)
    cvec = jnp.asarray(pts.plane if method in PLANE_METHODS else np.zeros(0))
    W = np.asarray(observation_matrix(robot, method, a, cvec, jnp.asarray(pts.Qi), jnp.asarray(pts.Qj), jnp.asarray(pts.Y)))
    return identifiable_from_W(robot, method, W, priority, include_gains, c, pts.constraint, time.perf_counter() - t0)


def gecaro_priority(robot: Robot, overrides: dict) -> np.ndarray:
    """robot.priority with some entries changed by name (a user priority matrix, §4)."""
    p = np.asarray(robot.priority, float).copy()
    for k, v in overrides.items():
        p[robot.index(k)] = v
    return p


@dataclasses.dataclass
class Calibration:
    """Outcome of `calibrate`: parameters, method unknowns (and their start), residual RMS per
    iteration and the step length taken at each iteration of the "gecaro" solver."""

    a: np.ndarray
    c: np.ndarray
    estimated: tuple[str, ...]
    iterations: int
    rms: np.ndarray  # RMS of the residual before each iteration and at the end
    converged: bool
    seconds: float
    c_start: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    step_lengths: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


@functools.partial(jax.jit, static_argnames=("robot", "method", "nr", "max_steps"))
def _lm_on_base(x, idx, Qi, Qj, Y, *, robot, method, nr, max_steps):
    """Levenberg-Marquardt (`jaxcal.fit.lm`, the core's solver) on the base entries x[idx], the others fixed;
    compiled once per robot/method/shapes.

    The iteration is the core's, the problem is not: a GECARO method's residual (seed 001 §3) runs over pairs
    of configurations (point/frame link, plane link 2, distance) and the method's plane coefficients, which a
    core `Problem` (one configuration and one device reading per sample) cannot express."""
    from jaxcal.fit import lm
    from jaxcal.fit.methods import stacked_residual

    def fn(xb, _):
        xf = x.at[idx].set(xb)
        return stacked_residual(robot, method, xf[:nr], xf[nr:], Qi, Qj, Y)

    sol = lm.least_squares(fn, x[idx], None, max_steps=max_steps, rtol=1e-12, atol=1e-15)
    return sol.z, sol.steps, sol.converged


SUFFICIENT_DECREASE = 1e-4  # Armijo constant of the ILS step-length control
MAX_HALVINGS = 30
STATIONARY = 1e-8  # |W_b dx| / |r| below this: r is orthogonal to the columns of W_b (a least-squares minimum)


def step_length(sum_sq, f0: float, slope: float) -> float:
    """Step length t of the ILS update x + t dx: the first of 1, 1/2, 1/4, ... (MAX_HALVINGS halvings)
    with sum_sq(t) <= f0 - SUFFICIENT_DECREASE * t * slope (Armijo), where slope = 2 |W_b dx|^2 is the
    decrease rate of the sum of squares along the Gauss-Newton direction dx = -W_b^+ r; 0 when none.

    Seed 001 (§6) takes the full linearised step; the halving only acts where the full step would
    raise the residual, which is what makes it diverge from large parameter errors."""
    t = 1.0
    for _ in range(MAX_HALVINGS + 1):
        f = sum_sq(t)
        if np.isfinite(f) and f <= f0 - SUFFICIENT_DECREASE * t * slope:
            return t
        t *= 0.5
    return 0.0


def start_unknowns(robot: Robot, points, a0, c0=None) -> np.ndarray:
    """Start of the method's own unknowns: c0 when given; for the unknown-plane methods the nearest
    plane to the model's tool points at a0 (seed 001 §3.3.1); otherwise the known plane of `points`."""
    from jaxcal.fit.methods import initial_plane

    if c0 is not None:
        return np.asarray(c0, float)
    if points.method in ("plane1_unknown", "plane2_unknown"):
        return initial_plane(robot, points.method, a0, points.Qi, points.Qj)
    return np.asarray(points.plane, float)


def _iterated_least_squares(res, jac, x, idx, max_iter, tol):
    """Seed 001 eq 9-10 iterated: dx = -W_b^+ r with W_b and r updated each iteration, the step
    length chosen by `step_length`. Returns (x, iterations, rms list, step lengths, converged)."""
    r = np.asarray(res(x))
    rms, steps, converged, it = [float(np.sqrt(np.mean(r ** 2)))], [], False, 0
    for it in range(1, max_iter + 1):
        Wb = np.asarray(jac(x))[:, idx]
        dx = -np.linalg.lstsq(Wb, r, rcond=None)[0]
        f0, Wdx = float(r @ r), Wb @ dx
        t = step_length(lambda t: float(np.sum(np.asarray(res(_moved(x, idx, t * dx))) ** 2)), f0, 2.0 * float(Wdx @ Wdx))
        steps.append(t)
        if t == 0.0:  # no step length lowers the residual: a minimum when r is orthogonal to W_b
            converged = np.linalg.norm(Wdx) <= STATIONARY * np.sqrt(f0)
            rms.append(rms[-1])
            break
        x = _moved(x, idx, t * dx)
        r = np.asarray(res(x))
        rms.append(float(np.sqrt(np.mean(r ** 2))))
        if np.linalg.norm(t * dx) < tol * (1 + np.linalg.norm(x[idx])) or rms[-1] < 1e-15:
            converged = True
            break
    return x, it, rms, np.array(steps), converged


def _moved(x, idx, d):
    """x with x[idx] += d (a copy)."""
    y = x.copy()
    y[idx] += d
    return y


def calibrate(robot: Robot, points, a0=None, c0=None, priority=None, include_gains=True, solver="gecaro",
              max_iter: int = 30, tol: float = 1e-14, n_configs: int = 40, seed: int = 0) -> Calibration:
    """Identify the base parameters of a method from generated/measured `points` (a `Points`).

    solver "gecaro": iterated linearised least squares on W_b (seed 001 eq 9-10: dx = -W_b^+ r,
    W_b and r updated each iteration) with a step-length control: the step is halved until the
    sum of squared residuals falls (Armijo rule, `step_length`); "lm": Levenberg-Marquardt
    (`jaxcal.fit.lm`) on the same base columns. Parameters outside the base set stay at a0.
    c0: start for the method's unknowns; by default the nearest plane to the tool points of the
    model at a0 for plane1_unknown / plane2_unknown (seed 001 §3.3.1), the points' known plane for
    plane1_known / plane2_known. The base set comes from `identifiable` at a0 (n_configs generated
    points, seed): measured points satisfy the constraint only for the true robot, so a W built on
    them at a0 would over-count (seed 001 §3.2, App. III)."""
    from jaxcal.fit.methods import stacked_residual

    if solver not in ("gecaro", "lm"):
        raise ValueError(f"unknown solver {solver!r}; expected 'gecaro' or 'lm'")
    method = points.method
    t0 = time.perf_counter()
    a0 = np.asarray(robot.nominal_np if a0 is None else a0, float)
    c0 = start_unknowns(robot, points, a0, c0)
    nr = robot.n_params
    Qi, Qj, Y = jnp.asarray(points.Qi), jnp.asarray(points.Qj), jnp.asarray(points.Y)
    x = np.concatenate([a0, c0])
    ident = identifiable(robot, method, n_configs=n_configs, seed=seed, priority=priority,
                         include_gains=include_gains, a=a0, plane=c0 if method in PLANE_METHODS else None)
    idx = np.sort(ident.basis.independent)
    res = lambda x: stacked_residual(robot, method, jnp.asarray(x[:nr]), jnp.asarray(x[nr:]), Qi, Qj, Y)  # noqa: E731
    steps = np.zeros(0)
    if solver == "gecaro":
        jac = lambda x: observation_matrix(robot, method, jnp.asarray(x[:nr]), jnp.asarray(x[nr:]), Qi, Qj, Y)  # noqa: E731
        x, it, rms, steps, converged = _iterated_least_squares(res, jac, x, idx, max_iter, tol)
    else:
        rms = [float(np.sqrt(np.mean(np.asarray(res(x)) ** 2)))]
        xb, n_steps, ok = _lm_on_base(jnp.asarray(x), jnp.asarray(idx), Qi, Qj, Y, robot=robot, method=method, nr=nr, max_steps=200)
        x[idx] = np.asarray(xb)
        it, converged = int(n_steps), bool(ok)
        rms.append(float(np.sqrt(np.mean(np.asarray(res(x)) ** 2))))
    names = ident.all_names
    return Calibration(x[:nr], x[nr:], tuple(names[i] for i in idx), it, np.array(rms), bool(converged),
                       time.perf_counter() - t0, c0, steps)
