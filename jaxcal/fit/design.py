"""Optimal measurement configurations: pick N of a candidate pool that maximise an observability index.

The observation matrix of N configurations is the stack of per-configuration blocks W_k (rows of
one sample, columns the base parameters), so its Gram matrix is a sum, M = sum_k W_k^T W_k, and
the singular values of W_b are sqrt(eig(M)). The blocks are computed once for the whole pool by
forward-mode autodiff; every candidate's score (M + W_c^T W_c, or M - W_i^T W_i + W_c^T W_c for an
exchange) is then an eigvalsh of a b x b matrix, vmapped over the pool.

Indices (all maximised; seed 001 App. III and the observability literature, see
`jaxcal.fit.identifiable.observability_indices`): "menq_borm" (s_1 ... s_b)^(1/b) / sqrt(m),
"min_singular" s_b, "condition" the inverse condition number s_b / s_1, "noise_amplification"
s_b^2 / s_1.

Search: greedy (one configuration at a time) then exchange passes (Fedorov: replace a chosen
configuration by the best pool candidate while the index improves). While the greedy stack has
fewer rows than base columns every index is zero, so the greedy stage scores by the regularised
log-determinant (D-optimality) until the rows reach the column count.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit.base import base_set
from jaxcal.fit.identifiable import observability_indices
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.fit.methods import METHODS, n_rows, observation_matrix
from jaxcal.fit.simulate import random_configurations
from jaxcal.forward import forward
from jaxcal.kin.model import Robot
from jaxcal.measure import as_device

INDICES = ("menq_borm", "min_singular", "condition", "noise_amplification")
SINGLE_CONFIG_METHODS = ("position", "location")


@dataclasses.dataclass(frozen=True)
class Design:
    """Chosen configurations `q` (n, n_inputs) = pool[`chosen`], their W_b's indices, the search trace."""

    q: np.ndarray
    chosen: np.ndarray
    index: str
    score: float  # the maximised index ("condition": the inverse condition number s_b / s_1)
    indices: dict
    condition: float
    base_names: tuple[str, ...]
    history: tuple[float, ...]  # index after the greedy stage, then after each accepted exchange
    exchanges: int
    seconds: float


def _index_of_eigs(lam, index: str):
    """Observability index (to maximise) from the eigenvalues of M = W_b^T W_b (ascending)."""
    s = jnp.sqrt(jnp.clip(lam, 0.0, None))
    if index == "menq_borm":  # the 1/sqrt(m) factor is the same for every candidate
        return jnp.exp(jnp.mean(jnp.log(jnp.maximum(s, 1e-300))))
    if index == "min_singular":
        return s[0]
    if index == "condition":
        return s[0] / s[-1]
    if index == "noise_amplification":
        return s[0] ** 2 / s[-1]
    raise ValueError(f"unknown observability index {index!r}; expected one of {INDICES}")


@functools.partial(jax.jit, static_argnames=("index", "regularised"))
def _scores_add(M, G, eps, *, index, regularised):
    """Score of M + G_c for every candidate Gram block G_c (vmapped)."""
    def one(Gc):
        if regularised:  # log det (M + G_c + eps I) = sum log(lambda + eps), by LU: ~15x faster than eigvalsh
            return jnp.linalg.slogdet(M + Gc + eps * jnp.eye(M.shape[0]))[1]
        return _index_of_eigs(jnp.linalg.eigvalsh(M + Gc), index)
    return jax.vmap(one)(G)


def configuration_blocks(robot: Robot, method_or_device, Q, a=None, d=None, sigmas=(1.0, 1.0)):
    """Per-configuration Jacobian blocks (N, rows, P), column names and priorities.

    method_or_device: a single-configuration GECARO method ("position", "location": columns are
    the robot parameters) or a device (kind string or `jc.make_device`: columns are the robot's
    then the device's parameters at d (default nominal), residuals weighted 1 / sigma with sigmas = (sigma_position,
    sigma_orientation), by default 1 per metre and per radian)."""
    Q = jnp.asarray(np.asarray(Q, float))
    if isinstance(method_or_device, str) and method_or_device in METHODS:
        if method_or_device not in SINGLE_CONFIG_METHODS:
            raise ValueError(f"method {method_or_device!r} needs pairs or constrained points; "
                             f"optimal selection supports {SINGLE_CONFIG_METHODS} or a device")
        a = robot.nominal if a is None else jnp.asarray(a, dtype=jnp.float64)
        Y = jnp.zeros((len(Q), 4, 4)) if method_or_device == "location" else jnp.zeros((len(Q), 3))
        W = observation_matrix(robot, method_or_device, a, jnp.zeros(0), Q, Q, Y)
        rows = n_rows(method_or_device)
        return np.asarray(W).reshape(len(Q), rows, -1), tuple(robot.names), np.asarray(robot.priority, float)
    device = as_device(method_or_device)
    d = device.nominal if d is None else jnp.asarray(d, dtype=jnp.float64)
    a_full = jnp.concatenate([robot.nominal if a is None else jnp.asarray(a, dtype=jnp.float64), d])
    w = residual_weights(device, *sigmas)
    Y = jax.vmap(device.read, (0, None))(forward(robot, a_full[: robot.n_params], Q), a_full[robot.n_params:])
    blocks = jax.vmap(lambda q, y: jax.jacfwd(lambda x: residuals(robot, device, x, q[None], y[None], w)[0])(a_full))(Q, Y)
    names = tuple(robot.names) + tuple(device.names)
    priority = np.concatenate([np.asarray(robot.priority, float), device.priority])
    return np.asarray(blocks), names, priority


def select_configurations(robot: Robot, method_or_device="position", n: int = 15, pool=None, index: str = "condition",
                          seed: int = 0, n_pool: int = 400, a=None, exchange: bool = True, max_passes: int = 20) -> Design:
    """Choose n configurations out of `pool` (array (N, n_inputs); default n_pool random ones drawn
    with `seed`) that maximise `index` of the base-parameter observation matrix W_b."""
    if index not in INDICES:
        raise ValueError(f"unknown observability index {index!r}; expected one of {INDICES}")
    t0 = time.perf_counter()
    pool = random_configurations(robot, n_pool, seed=seed) if pool is None else np.asarray(pool, float)
    if pool.ndim != 2 or pool.shape[1] != robot.n_inputs:
        raise ValueError(f"pool must be (N, {robot.n_inputs}) joint vectors, got shape {pool.shape}")
    if not 0 < n <= len(pool):
        raise ValueError(f"n must be between 1 and the pool size {len(pool)}, got {n}")
    blocks, names, priority = configuration_blocks(robot, method_or_device, pool, a)
    basis = base_set(blocks.reshape(-1, blocks.shape[-1]), priority)
    cols = np.sort(basis.independent)
    Wb = blocks[:, :, cols]
    G = jnp.asarray(np.einsum("kri,krj->kij", Wb, Wb))  # per-candidate Gram blocks
    b, rows = len(cols), Wb.shape[1]
    eps = 1e-9 * float(np.trace(np.asarray(G).mean(0))) / b
    chosen = _greedy(G, n, rows, b, eps, index)
    history = [_score(G, chosen, index)]
    swaps = 0
    if exchange:
        chosen, history, swaps = _exchange(G, chosen, index, history, max_passes)
    W = Wb[chosen].reshape(-1, b)
    ind = observability_indices(W)
    return Design(pool[chosen], np.asarray(chosen), index, history[-1], ind, ind["condition"],
                  tuple(names[i] for i in cols), tuple(history), swaps, time.perf_counter() - t0)


def _score(G, chosen, index):
    lam = jnp.linalg.eigvalsh(jnp.sum(G[np.asarray(chosen)], 0))
    return float(_index_of_eigs(lam, index))


def _greedy(G, n, rows, b, eps, index):
    """Add the best candidate one at a time (D-optimal while the rows are fewer than the columns)."""
    chosen, M = [], jnp.zeros(G.shape[1:])
    for k in range(n):
        regularised = (k + 1) * rows < b
        s = np.array(_scores_add(M, G, eps, index=index, regularised=regularised))
        s[chosen] = -np.inf
        best = int(np.argmax(s))
        chosen.append(best)
        M = M + G[best]
    return chosen


def _exchange(G, chosen, index, history, max_passes):
    """Replace chosen[i] by the best unchosen candidate while the index improves (Fedorov exchange)."""
    chosen = list(chosen)
    swaps = 0
    for _ in range(max_passes):
        improved = False
        for i in range(len(chosen)):
            M_without = jnp.sum(G[np.asarray(chosen)], 0) - G[chosen[i]]
            s = np.array(_scores_add(M_without, G, 0.0, index=index, regularised=False))
            s[chosen] = -np.inf
            best = int(np.argmax(s))
            if s[best] > history[-1] * (1 + 1e-9):
                chosen[i] = best
                history.append(float(s[best]))
                swaps += 1
                improved = True
        if not improved:
            break
    return chosen, history, swaps


def random_design_conditions(robot: Robot, method_or_device="position", n: int = 15, pool=None, draws: int = 20,
                             seed: int = 0, n_pool: int = 400, a=None) -> np.ndarray:
    """Condition numbers of W_b for `draws` random n-subsets of the pool (the baseline a design beats)."""
    pool = random_configurations(robot, n_pool, seed=seed) if pool is None else np.asarray(pool, float)
    blocks, _, priority = configuration_blocks(robot, method_or_device, pool, a)
    cols = np.sort(base_set(blocks.reshape(-1, blocks.shape[-1]), priority).independent)
    rng = np.random.default_rng(seed + 1)
    out = []
    for _ in range(draws):
        pick = rng.choice(len(pool), n, replace=False)
        out.append(np.linalg.cond(blocks[pick][:, :, cols].reshape(-1, len(cols))))
    return np.asarray(out)


# -- the next measurement campaign, from the current calibration ----------------------------------------
CRITERIA = ("d_optimal", "a_optimal")


@dataclasses.dataclass(frozen=True)
class NextCampaign:
    """Configurations `q` = pool[`chosen`] to measure next, in the order chosen, and what they are predicted to
    do to the standard errors of the calibration's estimated parameters (`names`; same data weights and
    residual standard deviation as the calibration)."""

    q: np.ndarray
    chosen: np.ndarray
    criterion: str
    names: tuple[str, ...]
    std_errors_now: np.ndarray
    std_errors_after: np.ndarray
    seconds: float


@functools.partial(jax.jit, static_argnames=("criterion",))
def _campaign_scores(M, G, *, criterion):
    """For every candidate block G_c: log det (M + G_c) (D-optimal) or -trace (M + G_c)^-1 (A-optimal)."""
    def one(Gc):
        A = M + Gc
        if criterion == "d_optimal":
            return jnp.linalg.slogdet(A)[1]
        return -jnp.trace(jnp.linalg.inv(A))
    return jax.vmap(one)(G)


def next_configurations(fit, n: int = 10, pool=None, criterion: str = "d_optimal", seed: int = 0,
                        n_pool: int = 400) -> NextCampaign:
    """Where to measure next: n configurations of `pool` (default n_pool random ones within the joint limits)
    chosen one at a time (greedy) to add the most information to what the calibration `fit` already has.

    The information of the estimated parameters is M = J^T J (J: the fit's weighted Jacobian, columns at
    their typical size, `core.x_scale`), and their covariance s^2 M^-1. A candidate adds its block G_c, computed
    at the calibrated robot and device with the fit's data weights. "d_optimal" maximises log det (M + sum G)
    (the volume of the confidence ellipsoid shrinks most); "a_optimal" minimises trace (M + sum G)^-1 (the mean
    variance in typical units: 1 cm, 0.01 rad, 1 for gains). Returns the predicted standard errors before and
    after, s^2 from the fit (the residual standard deviation it found)."""
    from jaxcal.fit.core import x_scale
    from jaxcal.measure.sessions import Sessions

    if criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r}; expected one of {CRITERIA}")
    if not fit.estimated:
        raise ValueError("the calibration estimated no parameter: nothing to plan for")
    t0 = time.perf_counter()
    robot = fit.robot
    device, d = fit.device, np.asarray(fit.device_params, float)
    if isinstance(device, Sessions):
        raise ValueError("planning from a calibration with several sessions is not supported: a new campaign brings "
                         "its own device frame; plan from a one-session calibration")
    pool = random_configurations(robot, n_pool, seed=seed) if pool is None else np.asarray(pool, float)
    if pool.ndim != 2 or pool.shape[1] != robot.n_inputs or not 0 < n <= len(pool):
        raise ValueError(f"pool must be (N >= n = {n}, {robot.n_inputs}) joint vectors, got shape {pool.shape}")
    sigmas = (fit.info.get("sigma_position", 1e-3), fit.info.get("sigma_orientation", 1e-3))
    blocks, names, _ = configuration_blocks(robot, device, pool, fit.a, d, sigmas)
    cols = np.array([fit.names.index(nm) for nm in fit.estimated])
    scale = x_scale(tuple(robot.units) + tuple(device.units))[cols]
    J = np.asarray(fit.jacobian)[:, cols] * scale
    M0 = J.T @ J
    Wc = blocks[:, :, cols] * scale
    G = jnp.asarray(np.einsum("kri,krj->kij", Wc, Wc))
    M, chosen = jnp.asarray(M0), []
    for _ in range(n):
        score = np.array(_campaign_scores(M, G, criterion=criterion))
        score[chosen] = -np.inf
        best = int(np.argmax(score))
        chosen.append(best)
        M = M + G[best]
    s2 = float(fit.sigma) ** 2 if fit.sigma is not None else 1.0
    se = lambda A: np.sqrt(np.maximum(np.diag(np.linalg.pinv(A)), 0.0) * s2) * scale  # noqa: E731
    return NextCampaign(pool[chosen], np.asarray(chosen), criterion, tuple(fit.estimated), se(M0), se(np.asarray(M)),
                        time.perf_counter() - t0)

