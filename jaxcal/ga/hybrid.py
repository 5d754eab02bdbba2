"""The thesis' hybrid calibration as one call (seed 000 §5.2.2, Figure 5.1, §8.3): the linear formulation's
solution seeds the GA's initial population, the GA runs until the fitness limit of eq 5.1a (or its
generation count), then Levenberg-Marquardt polishes the GA's best individual through the calibration core
(`core.calibrate`: base set at the GA's result, the core's one solver), and optionally Monte Carlo level 1
repeats the seeded GA (eq 5.7-5.9).

    linear (ch. 4, eq 4.27-4.29)  ->  GA seeded (§5.2.2), stop at sum_i ||X_m - X_0|| < epsilon (eq 5.1a)
                                  ->  LM polish (core)  [->  Monte Carlo level 1 of the seeded GA]

The fitness is eq 5.3-5.4 (w1 ||P_m - P_0||_2 + w2 ||R_m - R_0||_2 summed over the measurements); the
polish minimises the core's weighted least-squares residual of the same data (1/sigma weights), whose
optimum is the same pose fit for noise-free data.
"""

from __future__ import annotations

import dataclasses
import time

import jax.numpy as jnp
import numpy as np

from jaxcal.fit import core
from jaxcal.fit.data import Dataset
from jaxcal.fit.linear import LinearResult, linear_calibrate
from jaxcal.ga import montecarlo, runner
from jaxcal.ga.fitness import pose_fitness
from jaxcal.kin.model import Robot


@dataclasses.dataclass(frozen=True)
class HybridResult:
    """a: final robot parameters (polished, else the GA's); fitness: eq 5.3-5.4 at the linear solution, the
    GA's best and the polished parameters; linear / ga / polish / monte_carlo: each stage's own result;
    limit_generation: first generation whose best cost met the fitness limit (-1 never, None no limit);
    timings: seconds per stage."""

    a: np.ndarray
    fitness: dict
    linear: LinearResult
    ga: runner.GAResult
    polish: core.Calibration | None
    monte_carlo: montecarlo.Level1Result | None
    limit_generation: int | None
    timings: dict


def measured_poses(data: Dataset):
    """(R (N, 3, 3) or None, p (N, 3)) of the tip as the linear formulation takes them: readings of one
    marker point ("point") or one marker frame ("frame") in the base frame (identity device frame and marker)."""
    device = data.device
    d = np.asarray(device.nominal_np)
    if device.marker_reading not in ("point", "frame") or np.any(d != 0):
        raise ValueError("the linear formulation needs position or pose readings of the tool frame in the robot base "
                         f"frame (identity device frame and marker); got {device.kind!r} with device parameters {d}")
    y = np.asarray(data.y)
    if device.marker_reading == "point":
        return None, y.reshape(-1, 3)
    return y[:, :3, :3], y[:, :3, 3]


def _fitness(robot, data, a, w1, w2) -> float:
    dev = data.device
    return float(pose_fitness(robot, dev, jnp.concatenate([jnp.asarray(a), dev.nominal]), jnp.asarray(data.q),
                              jnp.asarray(data.y), w1, w2))


def polish_problem(robot: Robot, data: Dataset, a0, sigma_position=1e-3, sigma_orientation=1e-3) -> core.Problem:
    """The core Problem of the LM polish: the robot's free parameters from a0, device frame and marker known."""
    dev = data.device
    free = np.concatenate([np.asarray(robot.free_mask, bool), np.zeros(dev.n_params, bool)])
    return core.make_problem(robot, dev, data.q, data.y, weights=dev.weights(sigma_position, sigma_orientation), free=free,
                             a_ref=np.concatenate([np.asarray(a0, float), np.asarray(dev.nominal_np)]))


def hybrid(robot: Robot, data: Dataset, *, scheme="position", linear_tol=1e-9, population=50, generations=250,
           fitness_limit=None, w1=1.0, w2=1.0, seed=0, polish=True, settings: core.Settings = core.Settings(),
           monte_carlo: dict | None = None, **ga_kw) -> HybridResult:
    """Linear -> seeded GA (fitness-limit stop) -> LM polish through the core -> optional Monte Carlo.

    scheme: the linear formulation's measurement scheme ("position", the seed's choice for seeding, or
    "pose"); linear_tol: its RMSE stop. population / generations / w1 / w2 / seed and **ga_kw (bound,
    chunk, seed_spread, GA operators): `jaxcal.ga.calibrate`, seeded with the linear solution (`initial`).
    fitness_limit: epsilon of eq 5.1a (the seed's GUI "fitness limit"; 1e-5 in §6.2). polish: run
    core.calibrate from the GA's best individual (base set there). monte_carlo: keyword arguments of
    `montecarlo.level1` (tol, batch, max_runs, stop_on, ...) to repeat the seeded GA, or None."""
    t0 = time.perf_counter()
    R, p = measured_poses(data)
    lin = linear_calibrate(robot, data.q, R, p, scheme, update="pry", tol=linear_tol)
    a_lin = lin.a
    t1 = time.perf_counter()
    ga_kw = dict(ga_kw, w1=w1, w2=w2, fitness="pose", initial=a_lin)
    ga = runner.calibrate(robot, data, population=population, generations=generations, seed=seed,
                          fitness_limit=fitness_limit, **ga_kw)
    t2 = time.perf_counter()
    a = np.asarray(ga.a)
    cal = None
    if polish:
        cal = core.calibrate(polish_problem(robot, data, a), settings)
        a = cal.x[:robot.n_params]
    t3 = time.perf_counter()
    mc = None
    if monte_carlo is not None:
        mc = montecarlo.level1(robot, data, population=population, generations=generations, seed=seed, **ga_kw,
                               **monte_carlo)
    t4 = time.perf_counter()
    fit = {"nominal": _fitness(robot, data, robot.nominal_np, w1, w2), "linear": _fitness(robot, data, a_lin, w1, w2),
           "ga": float(ga.fitness), "polished": _fitness(robot, data, a, w1, w2) if polish else None}
    return HybridResult(a, fit, lin, ga, cal, mc, None if ga.limit_generation is None else int(ga.limit_generation[0]),
                        {"linear_s": t1 - t0, "ga_s": t2 - t1, "ga_compile_s": ga.timings["compile_s"], "polish_s": t3 - t2,
                         "monte_carlo_s": t4 - t3})
