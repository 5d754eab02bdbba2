"""`jc.ga.calibrate`: nonlinear calibration with the vmapped GA (seed 000 §5.2-5.3, Figure 5.1)."""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal import compiled
from jaxcal.fit.data import Dataset
from jaxcal.fit.identify import residual_weights
from jaxcal.ga import batched, core
from jaxcal.ga.fitness import full_vector, pose_fitness, residual_fitness
from jaxcal.kin.model import Robot


@dataclasses.dataclass
class GAResult:
    """Best individual of the GA as full vectors, and the fitness history per generation."""

    a: jnp.ndarray               # full robot parameter vector (len(robot.nominal))
    device_params: jnp.ndarray   # device parameters used/identified
    fitness: float               # best cost at the end
    best: np.ndarray             # (G,) best cost per generation (run 0)
    mean: np.ndarray             # (G,) mean cost per generation (run 0)
    free: tuple                  # names of the optimised parameters
    dg: np.ndarray               # (n_free,) best errors dg (run 0)
    runs_dg: np.ndarray          # (runs, n_free) best dg of every run
    runs_fitness: np.ndarray     # (runs,) final best cost of every run
    runs_best: np.ndarray        # (runs, G) best cost per generation of every run
    options: core.GAOptions
    timings: dict
    fitness_limit: float | None = None  # eq 5.1a's epsilon, when the GA was asked to stop there
    limit_generation: np.ndarray | None = None  # (runs,) first generation (1-based) whose best cost <= the limit, -1 never
    generations_run: int = 0     # generations actually run (a multiple of chunk; < generations after a limit stop)


@functools.lru_cache(maxsize=16)  # robots hash by identity: bounded
def engine(robot: Robot, device, free_idx: tuple, fitness_kind: str, w1: float, w2: float,
           opts: core.GAOptions, chunk: int, seed_spread: float):
    """Compiled (init_seeded, init_random, chunk) functions, cached per static setting. The data
    (q, y, a0, residual weights) is an argument, so a new dataset of the same shape reuses them.
    The pose fitness of PRY chains is evaluated for the whole population at once (`batched`),
    other robots/devices per individual, vmapped."""
    idx = jnp.asarray(free_idx)
    whole_population = fitness_kind == "pose" and batched.supports(robot, device)

    def population_fitness_of(pops, data):
        return batched.population_fitness(robot, device, data["a0"], free_idx, pops, data["q"], data["y"], w1, w2)

    def fitness_of(dg, data):
        a_full = full_vector(dg, data["a0"], idx)
        if fitness_kind == "pose":
            return pose_fitness(robot, device, a_full, data["q"], data["y"], w1, w2)
        return residual_fitness(robot, device, a_full, data["q"], data["y"], data["w"])

    fn = population_fitness_of if whole_population else fitness_of
    init_seeded, init_random = core.make_init_fn(fn, opts, seed_spread, batched=whole_population)
    chunk_fn = core.make_chunk_fn(fn, opts, chunk, batched=whole_population)
    return init_seeded, init_random, chunk_fn, jax.jit(jax.vmap(core.best_individual))


_COMPILED = {}
compiled.register(_COMPILED.clear)
compiled.register(engine.cache_clear)


def compiled_for_shapes(fn, *args):
    """AOT-compiled fn for these argument shapes (cached), so compile time is measured apart."""
    key = (id(fn), str(jax.tree_util.tree_map(lambda x: (jnp.shape(x), jnp.result_type(x)), args)))
    if key not in _COMPILED:
        _COMPILED[key] = (fn, fn.lower(*args).compile())
    return _COMPILED[key][1]


def _free_indices(free, robot: Robot, device):
    names = tuple(robot.names) + tuple(device.names)
    if free is None:
        return tuple(int(i) for i in np.flatnonzero(robot.free_mask)), names
    unknown = [n for n in free if n not in names]
    if unknown:
        raise KeyError(f"free: unknown parameter(s) {unknown}; robot/device parameters are {names}")
    return tuple(names.index(n) for n in free), names


def _bounds(bound, n):
    b = np.broadcast_to(np.asarray(bound, float), (n,))
    if np.any(b <= 0):
        raise ValueError(f"bound must be positive, got {bound}")
    return jnp.asarray(-b), jnp.asarray(b)


def _progress(total):
    try:
        from rich.progress import Progress
    except ImportError:  # pragma: no cover
        return None
    p = Progress(transient=True)
    p.start()
    return p, p.add_task("GA generations", total=total)


@dataclasses.dataclass
class Setup:
    """Everything a GA run on one dataset needs: compiled-function factories and their arguments."""

    opts: core.GAOptions
    free_idx: tuple
    names: tuple
    payload: dict
    lb: jnp.ndarray
    ub: jnp.ndarray
    a_full0: jnp.ndarray
    start: jnp.ndarray | None  # seeded initial individual (errors dg), or None for a random population
    init_seeded: object
    init_random: object
    chunk_fn: object
    best_fn: object
    chunk: int


def prepare(robot: Robot, data: Dataset, *, population=50, generations=250, free=None, bound=0.005,
            fitness="pose", w1=1.0, w2=1.0, a0=None, device_params=None, initial=None, seed_spread=0.1,
            sigma_position=1e-3, sigma_orientation=1e-3, chunk=25, **options) -> Setup:
    """Validate the arguments of `calibrate` and build the GA setup for `data`."""
    if fitness not in ("pose", "residual"):
        raise ValueError(f"fitness must be 'pose' or 'residual', got {fitness!r}")
    if data.q.shape[1] != robot.n_inputs:
        raise ValueError(f"data has {data.q.shape[1]} joint columns, robot {robot.name!r} has {robot.n_inputs} inputs")
    device = data.device
    free_idx, names = _free_indices(free, robot, device)
    chunk = int(min(chunk, generations))
    if generations % chunk:
        raise ValueError(f"generations={generations} must be a multiple of chunk={chunk}")
    opts = core.GAOptions(population=population, generations=generations, **options)
    a0 = robot.nominal if a0 is None else jnp.asarray(a0, jnp.float64)
    d0 = device.nominal if device_params is None else jnp.asarray(device_params, jnp.float64)
    a_full0 = jnp.concatenate([a0, d0])
    lb, ub = _bounds(bound, len(free_idx))
    payload = dict(q=jnp.asarray(data.q), y=jnp.asarray(data.y), a0=a_full0,
                   w=residual_weights(device, sigma_position, sigma_orientation))
    fns = engine(robot, device, free_idx, fitness, float(w1), float(w2), opts, chunk, float(seed_spread))
    start = None
    if initial is not None:
        fi = jnp.asarray(free_idx)
        start = jnp.concatenate([jnp.asarray(initial, jnp.float64), d0])[fi] - a_full0[fi]
    return Setup(opts, free_idx, names, payload, lb, ub, a_full0, start, *fns, chunk)


def first_at_or_below(best, limit) -> np.ndarray:
    """(runs,) the first generation (1-based) whose best cost is <= limit (eq 5.1a), -1 where none is."""
    hit = np.asarray(best) <= limit
    return np.where(hit.any(axis=-1), np.argmax(hit, axis=-1) + 1, -1)


def run(robot: Robot, data: Dataset, *, seed=0, runs=1, progress=False, fitness_limit=None, **kw):
    """Run `runs` independent GAs (vmapped) and return a GAResult. See `calibrate`."""
    st = prepare(robot, data, **kw)
    opts, payload, lb, ub, chunk = st.opts, st.payload, st.lb, st.ub, st.chunk
    generations, population = opts.generations, opts.population
    keys = jax.random.split(jax.random.PRNGKey(seed), runs)

    t0 = time.perf_counter()
    if st.start is None:
        init = compiled_for_shapes(st.init_random, keys, payload, lb, ub)
        state = init(keys, payload, lb, ub)
    else:
        init = compiled_for_shapes(st.init_seeded, keys, payload, lb, ub, st.start)
        state = init(keys, payload, lb, ub, st.start)
    chunk_c = compiled_for_shapes(st.chunk_fn, state, payload, lb, ub)
    jax.block_until_ready(state)
    compile_s = time.perf_counter() - t0

    t1 = time.perf_counter()
    bar = _progress(generations) if progress else None
    bests, means = [], []
    for _ in range(generations // chunk):
        state, b, m = chunk_c(state, payload, lb, ub)
        bests.append(b)
        means.append(m)
        if bar:
            jax.block_until_ready(b)
            bar[0].advance(bar[1], chunk)
        if fitness_limit is not None and np.all(np.asarray(b).min(axis=1) <= fitness_limit):
            break  # eq 5.1a: every run's best individual meets the required accuracy
    dg, cost = st.best_fn(state)
    jax.block_until_ready(dg)
    run_s = time.perf_counter() - t1
    if bar:
        bar[0].stop()

    best = np.concatenate([np.asarray(b) for b in bests], axis=1)
    mean = np.concatenate([np.asarray(m) for m in means], axis=1)
    a_best = np.asarray(full_vector(dg[0], st.a_full0, jnp.asarray(st.free_idx)))
    nr = robot.n_params
    done = best.shape[1]
    evals = runs * population * opts.subpopulations * (done + 1)
    return GAResult(
        a=jnp.asarray(a_best[:nr]), device_params=jnp.asarray(a_best[nr:]), fitness=float(cost[0]),
        best=best[0], mean=mean[0], free=tuple(st.names[i] for i in st.free_idx), dg=np.asarray(dg[0]),
        runs_dg=np.asarray(dg), runs_fitness=np.asarray(cost), runs_best=best, options=opts,
        timings={"compile_s": compile_s, "run_s": run_s, "evaluations": evals,
                 "evaluations_per_s": evals / run_s, "generations_per_s": runs * done / run_s},
        fitness_limit=fitness_limit,
        limit_generation=None if fitness_limit is None else first_at_or_below(best, fitness_limit),
        generations_run=done,
    )


def calibrate(robot: Robot, data: Dataset, population=50, generations=250, seed=0, **kw) -> GAResult:
    """Calibrate with the GA: minimise the seed's fitness (eq 5.3-5.4) over bounded errors dg.

    population: individuals per sub-population; generations: number of generations (a multiple
    of `chunk`, the generations per compiled call between progress updates).
    free: parameter names to optimise (robot and/or device names; default the robot's free mask).
    The device parameters (device frame, marker) are KNOWN at `device_params` (default: the
    device's nominal, identity frames) unless their names are listed in `free`.
    bound: variable bound on dg (seed: 0.005 m / rad), scalar or per free parameter.
    fitness: "pose" (w1 ||P_m - P_0|| + w2 ||R_m - R_0||_2 summed, eq 5.4) or "residual" (sum of
    squared jc residuals weighted by 1/sigma_position, 1/sigma_orientation; any device).
    initial: a full robot vector (e.g. a linear-formulation or LM solution) to seed the initial
    population (seed §5.2.2), spread +-seed_spread x bound around it; None = uniform in bounds.
    runs: independent GAs, vmapped (Monte Carlo level 1); `.a`, `.best`, `.mean` are run 0's.
    fitness_limit: the required accuracy epsilon of seed eq 5.1a (sum over the measurements of the pose
    error norms < epsilon): the GA stops after the first chunk of generations at whose end every run's best
    cost is <= epsilon (chunk=1 stops at the generation itself); `.limit_generation` gives, per run, the
    first generation that met it (-1: never), `.generations_run` how many ran.
    Other GA options (subpopulations, elite, crossover_fraction, selection, tournament_size,
    mutation_scale, mutation_shrink, migration_interval, migration_fraction): `core.GAOptions`.
    """
    return run(robot, data, population=population, generations=generations, seed=seed, **kw)
