"""Genetic algorithm for the nonlinear calibration formulation (seed 000 ch. 5).

The unknowns are the errors dg of the free parameters (seed eq 5.5-5.6: a = g + dg), bounded by
the seed's "variable bound" (+-0.005 m / rad by default). One generation (seed §5.2.3):
elite children survive, parents are chosen by fitness-proportional, rank or tournament
selection, a crossover fraction of the remaining children comes from scattered crossover and the
rest from Gaussian mutation (shrinking over the generations, clipped to the bounds), and every
`migration_interval` generations the best individuals of each sub-population replace the worst
of the next one (ring). Generations run in `lax.scan`; sub-populations and runs are `vmap`ped.
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


def _selection_weights(f, opts: GAOptions):
    """Selection probabilities of a sub-population with costs f (lower is better)."""
    if opts.selection == "proportional":
        # Fitness-proportional on the scaled fitness 1 / (1 + f / median f).
        fit = 1.0 / (1.0 + f / jnp.maximum(jnp.median(f), 1e-300))
        return fit / jnp.sum(fit)
    rank = jnp.argsort(jnp.argsort(f)) + 1.0  # 1 = best
    fit = 1.0 / jnp.sqrt(rank)  # rank scaling
    return fit / jnp.sum(fit)


def _select_parents(key, f, n, opts: GAOptions):
    """Indices of n parents."""
    if opts.selection == "tournament":
        cand = jax.random.randint(key, (n, opts.tournament_size), 0, f.shape[0])
        return jnp.take_along_axis(cand, jnp.argmin(f[cand], axis=1)[:, None], axis=1)[:, 0]
    return jax.random.choice(key, f.shape[0], (n,), p=_selection_weights(f, opts))


def next_generation(key, pop, f, lb, ub, progress, opts: GAOptions):
    """Children of one sub-population pop (P, n) with costs f (P,); progress in [0, 1]."""
    P, n = pop.shape
    n_elite = opts.elite
    n_xo = int(round(opts.crossover_fraction * (P - n_elite)))
    n_mut = P - n_elite - n_xo
    k_sel, k_mask, k_mut = jax.random.split(key, 3)
    order = jnp.argsort(f)
    elite = pop[order[:n_elite]]
    parents = pop[_select_parents(k_sel, f, 2 * n_xo + n_mut, opts)]
    pa, pb, pm = parents[:n_xo], parents[n_xo:2 * n_xo], parents[2 * n_xo:]
    if opts.crossover == "scattered":
        crossed = jnp.where(jax.random.bernoulli(k_mask, 0.5, (n_xo, n)), pa, pb)
    else:
        u = jax.random.uniform(k_mask, (n_xo, n), minval=-0.25, maxval=1.25)
        crossed = jnp.clip(pa + u * (pb - pa), lb, ub)
    sd = opts.mutation_scale * (ub - lb) * (1.0 - opts.mutation_shrink * progress)
    mutated = jnp.clip(pm + sd * jax.random.normal(k_mut, pm.shape), lb, ub)
    return jnp.concatenate([elite, crossed, mutated], axis=0)


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
    """GA state: (key, population (S, P, n), costs (S, P), generation counter)."""
    k0, k1 = jax.random.split(key)
    pop = initial_population(k0, lb, ub, opts, seed_individual, seed_spread)
    return k1, pop, jax.vmap(jax.vmap(fitness))(pop), jnp.int32(0)


def step(state, fitness, lb, ub, opts: GAOptions):
    """One generation of every sub-population, then migration. Returns (state, (best, mean))."""
    key, pops, fs, g = state
    key, sub = jax.random.split(key)
    progress = g / max(opts.generations - 1, 1)
    keys = jax.random.split(sub, pops.shape[0])
    children = jax.vmap(next_generation, (0, 0, 0, None, None, None, None))(keys, pops, fs, lb, ub, progress, opts)
    cf = jax.vmap(jax.vmap(fitness))(children)
    cf = jnp.where(jnp.isfinite(cf), cf, jnp.inf)
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


def make_chunk_fn(fitness_of, opts: GAOptions, n_generations: int):
    """jit(vmap over runs) of `run_chunk` for fitness_of(dg, data) with data a pytree of arrays."""

    def one(state, data, lb, ub):
        return run_chunk(state, functools.partial(fitness_of, data=data), lb, ub, opts, n_generations)

    return jax.jit(jax.vmap(one, (0, None, None, None)))


def make_init_fn(fitness_of, opts: GAOptions, seed_spread=0.1):
    """jit(vmap over runs) of `init_state`."""

    def one(key, data, lb, ub, seed_individual):
        return init_state(key, functools.partial(fitness_of, data=data), lb, ub, opts, seed_individual, seed_spread)

    def one_random(key, data, lb, ub):
        return init_state(key, functools.partial(fitness_of, data=data), lb, ub, opts)

    return (jax.jit(jax.vmap(one, (0, None, None, None, None))),
            jax.jit(jax.vmap(one_random, (0, None, None, None))))
