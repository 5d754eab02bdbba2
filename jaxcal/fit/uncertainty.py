"""Noise, uncertainty and confidence (seed 004 §3.5, §4.3.1, Appendix A.5).

- `linear_covariance`: the covariance of the estimate from the Jacobian at the solution, with
  measurement noise and actuator (joint) noise propagated through the model (eq 3.28-3.30),
  restricted to the base set so it exists for rank-deficient models.
- `monte_carlo`: N noise draws -> N identifications as one vmapped, compiled LM, chunked so memory
  stays bounded, sharded over the devices JAX sees (what the thesis found "prohibitive").
- `similarity`: the normalised eigenvalue metric of Appendix A.5 (eq A.51-A.57).
- `confidence_intervals` (eq 3.35-3.36 one at a time, eq 3.41-3.42 simultaneous), Mahalanobis
  distances and the chi-square Q-Q data of §3.5.3, outlier rejection (eq 4.2), the cost
  sensitivity along covariance eigenvectors (eq 4.5), and robust identification by iteratively
  re-weighted least squares.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.fit import core
from jaxcal.fit.data import Dataset
from jaxcal.fit.identify import identify, residual_weights, residuals
from jaxcal.fit.simulate import simulate
from jaxcal.forward import forward
from jaxcal.measure import as_device, key_normal
from jaxcal.shard import over_devices
from jaxcal.tails import chi2_ppf


# ------------------------------------------------------------------------------------------
# Linearised covariance
# ------------------------------------------------------------------------------------------
def linear_covariance(fit, data: Dataset, noise=None):
    """Covariance of the estimated parameters by linear analysis (seed 004 eq 3.28-3.30).

    For the weighted least-squares estimate with solver weights W = diag(1/sigma^2) (the fit's
    sigma_position / sigma_orientation), Sigma_a = A^-1 J^T W Sigma_y W J A^-1 with A = J^T W J.
    Sigma_y holds the measurement noise and the actuator repeatability mapped through the model:
    Sigma_y = Sigma_m + J_theta Sigma_theta J_theta^T per sample (eq 3.29). `noise` is a dict
    with "position", "orientation" (sd of the readings) and "actuator" (sd of the joints); by
    default the measurement noise equals the fit's sigmas and there is no actuator noise, and
    then Sigma_a = A^-1. Only the base-set columns enter, so A is regular.
    """
    robot, device = fit.robot, fit.device
    info = fit.info
    w_solver = np.asarray(residual_weights(device, info["sigma_position"], info["sigma_orientation"])) ** 2
    noise = noise or {"position": info["sigma_position"], "orientation": info["sigma_orientation"]}
    var_m = np.asarray(residual_weights(device, 1.0, 1.0))  # ones, one per residual component
    pos_comp = np.asarray(residual_weights(device, 1.0, np.inf)) > 0
    var_m = np.where(pos_comp, noise.get("position", 0.0) ** 2, noise.get("orientation", 0.0) ** 2) * var_m
    q, y = jnp.asarray(data.q), jnp.asarray(data.y)
    idx = info["estimated_index"]
    a_full = fit.a_full
    J = core.jacobian(robot, device, a_full, q, y, residual_weights(device, 1.0, 1.0))[:, idx]
    n, m = len(data), len(w_solver)
    Jb = J.reshape(n, m, -1)
    WJ = Jb * w_solver[None, :, None]
    A = np.einsum("nia,nib->ab", Jb, WJ)
    Ainv = np.linalg.pinv(A)
    s_q = noise.get("actuator", 0.0)
    if s_q:
        Jq = np.asarray(_joint_jacobians(robot, device, a_full, q, y))  # (N, m, n_inputs)
        Sy = np.einsum("nij,nkj->nik", Jq, Jq) * s_q**2 + np.eye(m)[None] * var_m[None, None, :]
    else:
        Sy = np.broadcast_to(np.eye(m) * var_m[None, :], (n, m, m))
    B = np.einsum("nia,nij,njb->ab", WJ, Sy, WJ)
    return Ainv @ B @ Ainv


@functools.partial(jax.jit, static_argnums=(0, 1))
def _joint_jacobians(robot, device, a_full, q, y):
    """d residual_i / d q_i per sample (unit weights), jitted: through a loop closure the eager
    version dispatched the closure solve op by op (19 s on the 3-D four-bar)."""
    ones = residual_weights(device, 1.0, 1.0)

    def sample_res(qi, yi):
        return residuals(robot, device, a_full, qi[None], yi[None], ones)[0]

    return jax.vmap(jax.jacfwd(sample_res))(q, y)


def similarity(A, B) -> float:
    """Normalised similarity metric of seed 004 eq A.56: sqrt(sum (lambda_A,i - lambda_B,i)^2) / lambda_M,
    eigenvalues sorted, lambda_M the largest eigenvalue of either. 0 when the spectra agree."""
    la = np.sort(np.linalg.eigvalsh(np.asarray(A)))[::-1]
    lb = np.sort(np.linalg.eigvalsh(np.asarray(B)))[::-1]
    lam_max = max(la[0], lb[0])
    return float(np.sqrt(np.sum((la - lb) ** 2)) / lam_max)


def confidence_intervals(a, cov, alpha: float = 0.05, simultaneous: bool = False):
    """(low, high) per parameter: a_i -/+ sqrt(chi2_k(1 - alpha) Sigma_ii) with k = 1 for one
    parameter at a time (eq 3.35-3.36) or k = dim(a) for the projection of the simultaneous
    ellipsoid (a - a_hat)^T Sigma^-1 (a - a_hat) = chi2_k(1 - alpha) (eq 3.41-3.42)."""
    a = np.asarray(a)
    k = len(a) if simultaneous else 1
    half = np.sqrt(chi2_ppf(1 - alpha, k) * np.diag(cov))
    return a - half, a + half


def mahalanobis_sq(samples, mean, cov):
    """d_i^2 = (x_i - mean)^T Sigma^-1 (x_i - mean)  (seed 004 eq 3.43)."""
    X = np.asarray(samples) - np.asarray(mean)
    return np.einsum("ij,jk,ik->i", X, np.linalg.pinv(cov), X)


def ellipsoid_coverage(samples, center, cov, alpha: float = 0.05):
    """Fraction of samples inside the 1 - alpha ellipsoid (eq 3.41), its Mahalanobis radius, and
    the radius that would hold 1 - alpha of the samples (the thesis: 86 % inside r = 6.2; 95 % needs 7.1)."""
    d2 = mahalanobis_sq(samples, center, cov)
    k = np.asarray(samples).shape[1]
    r2 = chi2_ppf(1 - alpha, k)
    return float(np.mean(d2 <= r2)), float(np.sqrt(r2)), float(np.sqrt(np.quantile(d2, 1 - alpha)))


def chi2_qq(samples):
    """Chi-square plot data (seed 004 §3.5.3): sorted d_i^2 about the sample mean/covariance against
    the chi2_p quantiles of (i - 1/2)/n, and their correlation (1 for a Gaussian sample)."""
    X = np.asarray(samples)
    d2 = np.sort(mahalanobis_sq(X, X.mean(0), np.cov(X.T)))
    n, p = X.shape
    quant = chi2_ppf((np.arange(1, n + 1) - 0.5) / n, p)
    return d2, quant, float(np.corrcoef(d2, quant)[0, 1])


def reject_outliers(samples, reference, k: float = 5.0):
    """Outlier mask by the distance r_o = ||a_i - a_0|| of each estimate from the reference
    (seed 004 eq 4.2); the threshold is median + k * MAD of r_o. Returns (keep mask, r_o, threshold)."""
    r = np.linalg.norm(np.asarray(samples) - np.asarray(reference), axis=1)
    med = np.median(r)
    mad = np.median(np.abs(r - med)) * 1.4826
    thr = med + k * max(mad, 1e-300)
    return r <= thr, r, float(thr)


def cost_sensitivity(fit, data: Dataset, cov, extent=None):
    """Sensitivity of the cost along each covariance eigenvector e_j (seed 004 eq 4.5):
    d rho_j = rho(a + s_j e_j) - rho(a), with s_j the half-width of the confidence ellipsoid
    along e_j (default sqrt(lambda_j)). The cost is the fit's weighted sum of squares, so with the
    linear covariance and the default extent every sensitivity is ~1 (one chi-square unit); with a
    common extent the sensitivities fall as 1/lambda_j, the inverse relation of Figure 4.20.
    Returns (eigenvalues, eigenvectors, sensitivities)."""
    lam, V = np.linalg.eigh(np.asarray(cov))
    order = np.argsort(lam)[::-1]
    lam, V = lam[order], V[:, order]
    s = np.sqrt(np.maximum(lam, 0.0)) if extent is None else np.broadcast_to(np.asarray(extent, float), lam.shape)
    idx = fit.info["estimated_index"]
    w = residual_weights(fit.device, fit.info["sigma_position"], fit.info["sigma_orientation"])
    q, y = jnp.asarray(data.q), jnp.asarray(data.y)
    cost = jax.jit(lambda a: jnp.sum(residuals(fit.robot, fit.device, a, q, y, w) ** 2))
    base = float(cost(fit.a_full))
    steps = jnp.asarray(fit.a_full)[None, :].repeat(len(lam), 0)
    steps = steps.at[:, idx].add(jnp.asarray((V * s[None, :]).T))
    sens = np.array([float(cost(a)) - base for a in steps])
    return lam, V, sens


def robust_identify(robot, data: Dataset, c: float = 3.0, iterations: int = 5, **kwargs):
    """Identification with outliers: iteratively re-weighted least squares with Tukey's biweight
    on the per-sample residual norm scaled by its median absolute deviation. Returns
    (fit, weights, rejected sample indices (weight 0))."""
    weights = np.ones(len(data))
    fit = identify(robot, data, **kwargs)
    for _ in range(iterations):
        pe, oe = fit.errors(data)
        e = pe if pe is not None else oe
        scale = 1.4826 * np.median(np.abs(e - np.median(e))) + np.median(e)
        u = e / (c * max(scale, 1e-15))
        new = np.where(u < 1, (1 - u**2) ** 2, 0.0)
        if np.allclose(new, weights, atol=1e-6):
            break
        weights = new
        fit = identify(robot, data, sample_weights=weights, **kwargs)
    return fit, weights, np.flatnonzero(weights == 0)


# ------------------------------------------------------------------------------------------
# Vectorised Monte Carlo identification
# ------------------------------------------------------------------------------------------
@functools.partial(jax.jit, static_argnames=("robot", "device"))
def _noisy_readings(robot, device, a_true, d, q, key, s_q, s_p, s_r):
    """One noisy reading set (seed 004 §4.3): actuator noise before the direct model, then
    measurement noise on the device reading."""
    k_actuator, k_device = jax.random.split(key)
    q_act = q + s_q * jax.random.normal(k_actuator, q.shape)
    tips = forward(robot, a_true, q_act)
    y = jax.vmap(device.read, (0, None))(tips, d)
    return device.add_noise(y, key_normal(k_device), s_p, s_r)


@functools.partial(jax.jit, static_argnames=("robot", "device"))
def _noisy_batch(robot, device, a_true, d, q, keys, s_q, s_p, s_r):
    """One noisy reading set per key; the noise levels are arguments, so one compile serves every level."""
    return jax.vmap(lambda k: _noisy_readings(robot, device, a_true, d, q, k, s_q, s_p, s_r))(keys)


@dataclasses.dataclass
class MonteCarloResult:
    names: tuple[str, ...]  # estimated parameters (the base set)
    estimates: np.ndarray  # (runs, len(names))
    converged: np.ndarray  # (runs,) bool, per-sample solver flag
    iterations: np.ndarray
    reference: np.ndarray  # noise-free estimate of the same parameters
    covariance_linear: np.ndarray
    timings: dict
    keep: np.ndarray  # outlier mask (eq 4.2) over the converged runs
    residual_norms: np.ndarray  # (runs,) 2-norm of the weighted residual after identification (eq 4.1)

    @property
    def covariance_mc(self):
        X = self.estimates[self.converged & self.keep]
        return np.cov(X.T)

    def summary(self) -> dict:
        X = self.estimates[self.converged & self.keep]
        cmc = self.covariance_mc
        inside, r95, r_emp = ellipsoid_coverage(X, X.mean(0), self.covariance_linear)
        _, _, qq = chi2_qq(X) if len(X) > X.shape[1] + 1 else (None, None, float("nan"))
        return {
            "runs": len(self.estimates), "converged": int(self.converged.sum()),
            "outliers": int((self.converged & ~self.keep).sum()),
            "similarity": similarity(self.covariance_linear, cmc),
            "inside_95": inside, "radius_95": r95, "radius_holding_95": r_emp, "qq_correlation": qq,
            "bias_over_std": float(np.max(np.abs(X.mean(0) - self.reference) / np.sqrt(np.diag(cmc)))),
            "identifications_per_s": len(self.estimates) / max(self.timings["run_s"], 1e-12),
        }

    def table(self) -> str:
        """Table 4.3 layout: diagonals and sorted eigenvalues of both covariances."""
        cl, cm = self.covariance_linear, self.covariance_mc
        el, em = np.sort(np.linalg.eigvalsh(cl))[::-1], np.sort(np.linalg.eigvalsh(cm))[::-1]
        lines = [f"{'parameter':<12}{'diag lin':>12}{'diag MC':>12}{'eig lin':>12}{'eig MC':>12}"]
        for i, n in enumerate(self.names):
            lines.append(f"{n:<12}{cl[i, i]:>12.3e}{cm[i, i]:>12.3e}{el[i]:>12.3e}{em[i]:>12.3e}")
        return "\n".join(lines)


def monte_carlo(robot, a_true, q, device="position", noise=None, runs: int = 100, known=(), seed: int = 0,
                chunk: int = 64, devices=None, sigma_position=1e-3, sigma_orientation=1e-3,
                max_steps: int = 50, solver: str | None = None, outlier_k: float = 5.0, start: str = "reference",
                free=None, base: bool = True) -> MonteCarloResult:
    """`runs` noisy data sets of the robot with parameters a_true at joint readings q, each
    identified, as vmapped compiled LM solves in chunks of `chunk` (seed 004 §4.3.1).

    The estimated set and the prior are those of the noise-free identification (`identify` with `free` and
    `base`: base=False estimates every free parameter, as the thesis' 26-parameter four-bar study). Every run starts
    from the noise-free estimate (`start="reference"`: the spread due to noise, in a few
    iterations) or from the nominal robot (`start="nominal"`: the whole identification, about 20
    LM iterations), with a fixed iteration budget and its own convergence flag. The default solver
    from the reference is Gauss-Newton on the normal equations by Cholesky: 4 steps for every draw
    (LM's trust region took up to 21 on some draws, and a vmapped loop runs as long as its slowest
    member), and batched Cholesky is what a GPU does well (batched QR was 7x slower on an H100).
    From nominal it is LM. `devices`: the JAX
    devices to shard the runs over (default: all local devices; [] or one device: no sharding).
    """
    dev = as_device(device)
    solver = solver or ("gn_normal" if start == "reference" else "lm")
    noise = noise or {}
    s_q, s_p, s_r = (float(noise.get(k, 0.0)) for k in ("actuator", "position", "orientation"))
    clean = simulate(robot, a_true, q, dev)
    ref = identify(robot, clean, known=known, sigma_position=sigma_position, sigma_orientation=sigma_orientation,
                   free=free, base=base)
    idx = ref.info["estimated_index"]
    cov_lin = linear_covariance(ref, clean, {"position": s_p, "orientation": s_r, "actuator": s_q})
    if devices is None:
        devices = jax.devices()
    devices = list(devices) if devices is not None and len(devices) > 1 else None  # [] or one device: no sharding
    n_dev = 1 if devices is None else len(devices)
    chunk = max(n_dev, (chunk // n_dev) * n_dev)
    mask = np.zeros(len(ref.names))
    mask[idx] = 1.0
    if start not in ("reference", "nominal"):
        raise ValueError(f"start must be 'reference' or 'nominal', got {start!r}")
    a_prior = jnp.asarray(ref.a_full)
    if start == "nominal":  # keep the noise-free frames but put the robot back at nominal, as identify starts
        a_prior = a_prior.at[idx].set(jnp.concatenate([robot.nominal, dev.nominal])[idx])
    problem = core.make_problem(robot, dev, clean.q, clean.y, weights=residual_weights(dev, sigma_position, sigma_orientation),
                                free=np.isin(np.arange(len(ref.names)), idx), a_ref=np.asarray(a_prior))
    # O(1) starting residual for LM (as `core.Problem.args`), but from the noise-free reference the residual is ~0:
    # divide only by an RMS above 1 (the noise term is ~1 when the sigmas are the noise levels)
    r0 = core.weighted_residuals(robot, dev, a_prior, clean.q, clean.y, problem.w)
    args = dict(problem.args(idx, 0.0, np.asarray(a_prior)), w=jnp.asarray(problem.w / max(1.0, np.sqrt(np.mean(r0**2)))))
    settings = core.Settings(solver, max_steps)
    keys = jax.random.split(jax.random.PRNGKey(seed), runs)
    gen = functools.partial(_noisy_batch, robot, dev, jnp.asarray(a_true), dev.nominal, jnp.asarray(clean.q),
                            s_q=s_q, s_p=s_p, s_r=s_r)

    def solve_chunk(ys, shared):
        out = core.solve_batch(problem, shared["x0"], dict(shared["args"], y=ys), settings, ("y",))
        solve_chunk.compile_s += out[4]
        return out[:4]

    solve_chunk.compile_s = 0.0
    est, ok, its, norms = [], [], [], []
    t0 = time.perf_counter()
    for first in range(0, runs, chunk):
        k = keys[first:first + chunk]
        pad = chunk - len(k)
        if pad:
            k = jnp.concatenate([k, jnp.repeat(k[-1:], pad, 0)])
        x, conv, steps, cost = over_devices(solve_chunk, gen(k), {"x0": a_prior, "args": args}, devices or [])
        norms.append(np.sqrt(np.asarray(cost))[: chunk - pad])
        est.append(np.asarray(x)[: chunk - pad, :][:, idx])
        ok.append(np.asarray(conv)[: chunk - pad])
        its.append(np.asarray(steps)[: chunk - pad])
    compile_s = solve_chunk.compile_s
    run_s = time.perf_counter() - t0 - compile_s
    est, ok, its, norms = np.concatenate(est), np.concatenate(ok), np.concatenate(its), np.concatenate(norms)
    reference = np.asarray(ref.a_full)[idx]
    keep = np.zeros(len(est), bool)
    if ok.any():
        keep_ok, _, _ = reject_outliers(est[ok], reference, outlier_k)
        keep[np.flatnonzero(ok)] = keep_ok
    return MonteCarloResult(tuple(ref.names[i] for i in idx), est, ok, its, reference, cov_lin,
                            {"compile_s": compile_s, "run_s": run_s, "devices": n_dev, "chunk": chunk, "solver": solver},
                            keep, norms)


__all__ = ["MonteCarloResult", "chi2_qq", "confidence_intervals", "cost_sensitivity", "ellipsoid_coverage",
           "linear_covariance", "mahalanobis_sq", "monte_carlo", "reject_outliers", "robust_identify", "similarity"]
