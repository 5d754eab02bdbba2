"""Identifiable (base) parameters per calibration method and observability indices.

seed 001 Appendix III: the observation matrix W of a method (autodiff Jacobian of its residual
at generated points) is QR-decomposed with its columns in priority order; the base set is the
first independent columns (|R_ii| > tau = c eps max|R_jj|, eq 34), zero columns have no effect
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
    """Menq-Borm O1, minimum singular value, condition number, noise amplification index."""
    Wb = np.asarray(Wb, float)
    s = np.linalg.svd(Wb, compute_uv=False)
    m, b = Wb.shape
    return {
        "menq_borm": float(np.exp(np.mean(np.log(s))) / np.sqrt(m)),
        "min_singular": float(s[-1]),
        "condition": float(s[0] / s[-1]),
        "noise_amplification": float(s[-1] ** 2 / s[0]),
    }


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
    bs = base_set(W, p, c)
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
    that W has at least twice as many rows as columns."""
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
    """Outcome of `calibrate`: parameters, method unknowns, residual RMS per iteration."""

    a: np.ndarray
    c: np.ndarray
    estimated: tuple[str, ...]
    iterations: int
    rms: np.ndarray  # RMS of the residual before each iteration and at the end
    converged: bool
    seconds: float


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


def calibrate(robot: Robot, points, a0=None, c0=None, priority=None, include_gains=True, solver="gecaro",
              max_iter: int = 30, tol: float = 1e-14, n_configs: int = 40, seed: int = 0) -> Calibration:
    """Identify the base parameters of a method from generated/measured `points` (a `Points`).

    solver "gecaro": iterated linearised least squares on W_b (seed 001 eq 9-10: dx = -W_b^+ r,
    W_b and r updated each iteration); "lm": Levenberg-Marquardt (`jaxcal.fit.lm`) on the same base
    columns. Parameters outside the base set stay at a0. c0: start for the plane coefficients
    (unknown-plane methods; default the points' plane). The base set comes from `identifiable`
    at a0 (n_configs generated points, seed): measured points satisfy the constraint only for
    the true robot, so a W built on them at a0 would over-count (seed 001 §3.2, App. III)."""
    from jaxcal.fit.methods import stacked_residual

    method = points.method
    t0 = time.perf_counter()
    a0 = np.asarray(robot.nominal_np if a0 is None else a0, float)
    c0 = np.asarray(points.plane if c0 is None else c0, float)
    nr = robot.n_params
    Qi, Qj, Y = jnp.asarray(points.Qi), jnp.asarray(points.Qj), jnp.asarray(points.Y)
    x = np.concatenate([a0, c0])
    ident = identifiable(robot, method, n_configs=n_configs, seed=seed, priority=priority,
                         include_gains=include_gains, a=a0, plane=c0 if method in PLANE_METHODS else None)
    idx = np.sort(ident.basis.independent)
    res = lambda x: stacked_residual(robot, method, x[:nr], x[nr:], Qi, Qj, Y)  # noqa: E731
    rms = [float(np.sqrt(np.mean(np.asarray(res(jnp.asarray(x))) ** 2)))]
    converged, it = False, 0
    if solver == "gecaro":
        for it in range(1, max_iter + 1):
            xj = jnp.asarray(x)
            r = np.asarray(res(xj))
            Wb = np.asarray(observation_matrix(robot, method, xj[:nr], xj[nr:], Qi, Qj, Y))[:, idx]
            dx = -np.linalg.lstsq(Wb, r, rcond=None)[0]
            x[idx] += dx
            rms.append(float(np.sqrt(np.mean(np.asarray(res(jnp.asarray(x))) ** 2))))
            if np.linalg.norm(dx) < tol * (1 + np.linalg.norm(x[idx])) or rms[-1] < 1e-15:
                converged = True
                break
    elif solver == "lm":
        xb, steps, ok = _lm_on_base(jnp.asarray(x), jnp.asarray(idx), Qi, Qj, Y, robot=robot, method=method, nr=nr, max_steps=200)
        x[idx] = np.asarray(xb)
        it, converged = int(steps), bool(ok)
        rms.append(float(np.sqrt(np.mean(np.asarray(res(jnp.asarray(x))) ** 2))))
    else:
        raise ValueError(f"unknown solver {solver!r}; expected 'gecaro' or 'lm'")
    names = ident.all_names
    return Calibration(x[:nr], x[nr:], tuple(names[i] for i in idx), it, np.array(rms), converged,
                       time.perf_counter() - t0)
