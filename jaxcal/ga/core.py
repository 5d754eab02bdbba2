"""Genetic algorithm for the nonlinear calibration formulation (seed 000 ch. 5).

The unknowns are the errors dg of the free parameters (seed eq 5.5-5.6: a = g + dg), bounded by
the seed's "variable bound" (+-0.005 m / rad by default). One generation (seed §5.2.3):
elite children survive, parents are chosen by fitness-proportional, rank or tournament
selection, a crossover fraction of the remaining children comes from scattered or intermediate
crossover and the rest from Gaussian mutation (shrinking over the generations, clipped to the bounds), and every
`migration_interval` generations the best individuals of each sub-population replace the worst
of the next one (ring). Generations run in `lax.scan`; sub-populations and runs are `vmap`ped.
Per generation each sub-population is sorted once, and one key split gives one block of uniform
draws that selection, crossover and mutation share; the fitness sees the whole population at once.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

SELECTIONS = ("proportional", "rank", "tournament")


@dataclasses.dataclass(frozen=True)
class GAOptions:
    """Static GA settings (hashable: a jit static argument)."""

    population: int = 50          # individuals per sub-population
    subpopulations: int = 1
    elite: int = 2
    crossover_fraction: float = 0.8
    selection: str = "rank"
    crossover: str = "intermediate"  # "scattered" (random gene mask) or "intermediate" (line, extension 0.25)
    tournament_size: int = 4
    mutation_scale: float = 0.1   # Gaussian sd as a fraction of the bound width, generation 0
    mutation_shrink: float = 1.0  # sd falls linearly to (1 - shrink) x initial at the last generation
    migration_interval: int = 20
    migration_fraction: float = 0.2
    generations: int = 250

    def __post_init__(self):
        if self.selection not in SELECTIONS:
            raise ValueError(f"unknown selection {self.selection!r}; expected one of {SELECTIONS}")
        if not 0 <= self.elite < self.population:
            raise ValueError(f"elite={self.elite} must be in [0, population={self.population})")
        if self.crossover not in ("scattered", "intermediate"):
            raise ValueError(f"unknown crossover {self.crossover!r}; expected 'scattered' or 'intermediate'")
        if not 0.0 <= self.crossover_fraction <= 1.0:
            raise ValueError(f"crossover_fraction={self.crossover_fraction} must be in [0, 1]")


def _rank_cdf(P):
    """Cumulative selection probabilities of sorted positions 0..P-1 under rank scaling 1/sqrt(rank)."""
    w = 1.0 / jnp.sqrt(jnp.arange(1, P + 1, dtype=jnp.float64))
    return jnp.cumsum(w) / jnp.sum(w)


def _select_sorted(u_sel, u_tour, f_sorted, opts: GAOptions):
    """Positions (into the population sorted best first) of the parents.

    rank: probability of position k proportional to 1/sqrt(k + 1); proportional: to the scaled
    fitness 1 / (1 + f / median f); tournament: the best of `tournament_size` uniform draws, which
    on a sorted population is the smallest drawn position. u_sel (n,) and u_tour (n, size) uniform."""
    P = f_sorted.shape[0]
    if opts.selection == "tournament":
        return jnp.min(jnp.minimum((u_tour * P).astype(jnp.int32), P - 1), axis=1)
    if opts.selection == "rank":
        cdf = _rank_cdf(P)
    else:
        median = 0.5 * (f_sorted[(P - 1) // 2] + f_sorted[P // 2])
        fit = 1.0 / (1.0 + f_sorted / jnp.maximum(median, 1e-300))
        cdf = jnp.cumsum(fit) / jnp.sum(fit)
    return jnp.minimum(jnp.searchsorted(cdf, u_sel), P - 1)


def draw_counts(P, n, opts: GAOptions):
    """(n_elite, n_crossover, n_mutation, number of uniform draws) of one generation of one sub-population."""
    n_xo = int(round(opts.crossover_fraction * (P - opts.elite)))
    n_mut = P - opts.elite - n_xo
    n_par = 2 * n_xo + n_mut
    n_tour = n_par * opts.tournament_size if opts.selection == "tournament" else 0
    return opts.elite, n_xo, n_mut, n_par + n_tour + n_xo * n + n_mut * n


def next_generation(u, pop, f, lb, ub, progress, opts: GAOptions):
    """Children of one sub-population pop (P, n) with costs f (P,); progress in [0, 1].

    u: this generation's uniform draws (draw_counts(...)[3],) for selection, crossover and
    mutation; the population is sorted once and every operator works on the sorted order."""
    P, n = pop.shape
    n_elite, n_xo, n_mut, _ = draw_counts(P, n, opts)
    n_par = 2 * n_xo + n_mut
    order = jnp.argsort(f)
    pop_sorted, f_sorted = pop[order], f[order]
    u_sel, rest = u[:n_par], u[n_par:]
    n_tour = n_par * opts.tournament_size if opts.selection == "tournament" else 0
    u_tour, rest = rest[:n_tour].reshape(n_par, -1), rest[n_tour:]
    u_xo, u_mut = rest[:n_xo * n].reshape(n_xo, n), rest[n_xo * n:].reshape(n_mut, n)
    parents = pop_sorted[_select_sorted(u_sel, u_tour, f_sorted, opts)]
    pa, pb, pm = parents[:n_xo], parents[n_xo:2 * n_xo], parents[2 * n_xo:]
    if opts.crossover == "scattered":
        crossed = jnp.where(u_xo < 0.5, pa, pb)
    else:
        crossed = jnp.clip(pa + (1.5 * u_xo - 0.25) * (pb - pa), lb, ub)  # line extension 0.25 each side
    sd = opts.mutation_scale * (ub - lb) * (1.0 - opts.mutation_shrink * progress)
    normal = jnp.sqrt(2.0) * jax.scipy.special.erfinv(jnp.clip(2.0 * u_mut - 1.0, -1.0 + 1e-16, 1.0 - 1e-16))
    mutated = jnp.clip(pm + sd * normal, lb, ub)
    return jnp.concatenate([pop_sorted[:n_elite], crossed, mutated], axis=0)


def migrate(pops, fs, opts: GAOptions):
    """Best individuals of sub-population i replace the worst of sub-population i+1 (ring)."""
    S, P, _ = pops.shape
    k = max(1, int(round(opts.migration_fraction * P)))
    if S == 1:
        return pops, fs
    order = jnp.argsort(fs, axis=1)
    best = jnp.take_along_axis(pops, order[:, :k, None], axis=1)
    best_f = jnp.take_along_axis(fs, order[:, :k], axis=1)
    incoming, incoming_f = jnp.roll(best, 1, axis=0), jnp.roll(best_f, 1, axis=0)
    worst = order[:, P - k:]
    rows = jnp.arange(S)[:, None]
    return pops.at[rows, worst].set(incoming), fs.at[rows, worst].set(incoming_f)


def initial_population(key, lb, ub, opts: GAOptions, seed_individual=None, seed_spread=0.1):
    """(S, P, n) population: uniform within the bounds, or around a seed individual (e.g. the
    linear-formulation solution, seed §5.2.2): the seed itself plus uniform noise of
    +-seed_spread x the bound half-width, clipped to the bounds."""
    S, P = opts.subpopulations, opts.population
    u = jax.random.uniform(key, (S, P, lb.shape[0]))
    if seed_individual is None:
        return lb + u * (ub - lb)
    half = 0.5 * (ub - lb) * seed_spread
    pop = jnp.clip(seed_individual + (2.0 * u - 1.0) * half, lb, ub)
    return pop.at[:, 0].set(jnp.clip(seed_individual, lb, ub))


def init_state(key, fitness, lb, ub, opts: GAOptions, seed_individual=None, seed_spread=0.1):
    """GA state: (key, population (S, P, n), costs (S, P), generation counter).
    fitness maps a population (..., n) to costs (...)."""
    k0, k1 = jax.random.split(key)
    pop = initial_population(k0, lb, ub, opts, seed_individual, seed_spread)
    return k1, pop, fitness(pop), jnp.int32(0)


def step(state, fitness, lb, ub, opts: GAOptions):
    """One generation of every sub-population, then migration. Returns (state, (best, mean)).
    One key split and one block of uniform draws per generation."""
    key, pops, fs, g = state
    key, sub = jax.random.split(key)
    S, P, n = pops.shape
    progress = g / max(opts.generations - 1, 1)
    u = jax.random.uniform(sub, (S, draw_counts(P, n, opts)[3]))
    children = jax.vmap(next_generation, (0, 0, 0, None, None, None, None))(u, pops, fs, lb, ub, progress, opts)
    cf = fitness(children)
    cf = jnp.where(jnp.isfinite(cf), cf, jnp.inf)
    if S > 1:
        do_migrate = (g + 1) % opts.migration_interval == 0
        mp, mf = migrate(children, cf, opts)
        children, cf = jnp.where(do_migrate, mp, children), jnp.where(do_migrate, mf, cf)
    finite = jnp.where(jnp.isfinite(cf), cf, jnp.nan)
    return (key, children, cf, g + 1), (jnp.min(cf), jnp.nanmean(finite))


def run_chunk(state, fitness, lb, ub, opts: GAOptions, n_generations: int):
    """n_generations generations in one lax.scan; returns (state, best (G,), mean (G,))."""
    body = lambda s, _: step(s, fitness, lb, ub, opts)  # noqa: E731
    state, (best, mean) = jax.lax.scan(body, state, None, length=n_generations)
    return state, best, mean


def best_individual(state):
    """(dg, cost) of the best individual over all sub-populations."""
    _, pops, fs, _ = state
    flat_f = fs.reshape(-1)
    i = jnp.argmin(flat_f)
    return pops.reshape(-1, pops.shape[-1])[i], flat_f[i]


def jit_cpu_options(fn):
    """jax.jit without XLA's CPU "ynn" fusions: in XLA 0.10 its reduce fusion made the population-wide
    fitness 10-30x slower for populations of 1000 and more (measured)."""
    options = {"xla_cpu_experimental_ynn_fusion_type": ""} if jax.default_backend() == "cpu" else None
    return jax.jit(fn, compiler_options=options)


def population_fitness(fitness_of, batched: bool):
    """fitness(pops (..., n), data) -> costs (...): fitness_of itself when it is `batched` (takes a
    whole population), else fitness_of(dg, data) of one individual vmapped over the leading axes."""
    if batched:
        return fitness_of

    def per_individual(pops, data):
        flat = pops.reshape(-1, pops.shape[-1])
        return jax.vmap(lambda dg: fitness_of(dg, data))(flat).reshape(pops.shape[:-1])

    return per_individual


def make_chunk_fn(fitness_of, opts: GAOptions, n_generations: int, batched: bool = False):
    """jit(vmap over runs) of `run_chunk` for fitness_of(dg, data) with data a pytree of arrays
    (or fitness_of(pops, data) on whole populations when batched)."""
    fit = population_fitness(fitness_of, batched)

    def one(state, data, lb, ub):
        return run_chunk(state, functools.partial(fit, data=data), lb, ub, opts, n_generations)

    return jit_cpu_options(jax.vmap(one, (0, None, None, None)))


def make_init_fn(fitness_of, opts: GAOptions, seed_spread=0.1, batched: bool = False):
    """jit(vmap over runs) of `init_state` (seeded and random initial populations)."""
    fit = population_fitness(fitness_of, batched)

    def one(key, data, lb, ub, seed_individual):
        return init_state(key, functools.partial(fit, data=data), lb, ub, opts, seed_individual, seed_spread)

    def one_random(key, data, lb, ub):
        return init_state(key, functools.partial(fit, data=data), lb, ub, opts)

    return jit_cpu_options(jax.vmap(one, (0, None, None, None, None))), jit_cpu_options(jax.vmap(one_random, (0, None, None, None)))
