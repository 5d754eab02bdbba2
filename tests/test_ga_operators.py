"""GA operators (seed 000 §5.2.3) checked against their definitions, written out by hand here:
elitism, rank / fitness-proportional / tournament selection, scattered and intermediate crossover,
Gaussian mutation with a shrinking spread, ring migration, and the seeded initial population."""

from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxcal.ga import core

P, N = 10, 3
LB, UB = np.array([-1.0, -2.0, -0.5]), np.array([1.0, 2.0, 0.5])


def _population(seed=0):
    rng = np.random.default_rng(seed)
    pop = LB + rng.uniform(size=(P, N)) * (UB - LB)
    f = rng.permutation(P).astype(float) + rng.uniform(0, 0.1, P)  # distinct costs in shuffled order
    return pop, f


def _hand_cdf(weights):
    w = np.asarray(weights, float)
    return np.cumsum(w) / w.sum()


def _hand_pick(cdf, u):
    """Roulette wheel: the first position whose cumulative probability reaches u."""
    return np.array([min(int(np.argmax(cdf >= x)) if np.any(cdf >= x) else len(cdf) - 1, len(cdf) - 1) for x in u])


def _draws(opts, seed=1):
    return np.random.default_rng(seed).uniform(size=core.draw_counts(P, N, opts)[3])


@pytest.mark.parametrize("selection", ["rank", "proportional"])
def test_roulette_selection_follows_its_probabilities(selection):
    """rank: P(position k) proportional to 1/sqrt(k + 1); proportional: to 1 / (1 + f_k / median f).
    Draws just below and just above each cumulative probability land on positions k and k + 1."""
    opts = core.GAOptions(population=P, selection=selection)
    f_sorted = np.sort(_population()[1])
    weights = 1.0 / np.sqrt(np.arange(1, P + 1)) if selection == "rank" else 1.0 / (1.0 + f_sorted / np.median(f_sorted))
    cdf = _hand_cdf(weights)
    u = np.concatenate([cdf[:-1] - 1e-9, cdf[:-1] + 1e-9, [0.0, 1.0 - 1e-12]])
    got = np.asarray(core._select_sorted(jnp.asarray(u), jnp.zeros((len(u), 0)), jnp.asarray(f_sorted), opts))
    np.testing.assert_array_equal(got, _hand_pick(cdf, u))
    np.testing.assert_array_equal(got[: P - 1], np.arange(P - 1))
    np.testing.assert_array_equal(got[P - 1: 2 * P - 2], np.arange(1, P))


def test_tournament_selection_is_the_best_of_its_draws():
    """Each parent: tournament_size positions drawn uniformly; on a population sorted best first the
    winner is the smallest position drawn."""
    opts = core.GAOptions(population=P, selection="tournament", tournament_size=4)
    u_tour = np.random.default_rng(2).uniform(size=(200, 4))
    f_sorted = np.sort(_population()[1])
    got = np.asarray(core._select_sorted(jnp.zeros(200), jnp.asarray(u_tour), jnp.asarray(f_sorted), opts))
    np.testing.assert_array_equal(got, np.floor(u_tour * P).astype(int).min(axis=1))


def _split_draws(u, opts):
    """The draws of one generation in the order next_generation uses them."""
    _, n_xo, n_mut, _ = core.draw_counts(P, N, opts)
    n_par = 2 * n_xo + n_mut
    n_tour = n_par * opts.tournament_size if opts.selection == "tournament" else 0
    u_sel = u[:n_par]
    u_xo = u[n_par + n_tour: n_par + n_tour + n_xo * N].reshape(n_xo, N)
    u_mut = u[n_par + n_tour + n_xo * N:].reshape(n_mut, N)
    return u_sel, u_xo, u_mut


@pytest.mark.parametrize("crossover", ["scattered", "intermediate"])
def test_next_generation_is_elite_crossover_and_mutation_by_definition(crossover):
    """Children = the `elite` best unchanged, then crossover children of parent pairs (scattered: each
    gene from parent a where its draw < 0.5, else from b; intermediate: a + (1.5 u - 0.25)(b - a), a
    line extended 0.25 beyond both parents, clipped to the bounds), then mutants p + sd z with
    z = Phi^-1(u) and sd = scale (ub - lb)(1 - shrink progress), clipped to the bounds."""
    opts = core.GAOptions(population=P, elite=2, crossover_fraction=0.5, selection="rank", crossover=crossover,
                          mutation_scale=0.3, mutation_shrink=0.5)
    n_elite, n_xo, n_mut, _ = core.draw_counts(P, N, opts)
    assert (n_elite, n_xo, n_mut) == (2, 4, 4)  # round(0.5 (10 - 2)) crossover children, the rest mutants
    pop, f = _population()
    u = _draws(opts)
    progress = 0.4
    kids = np.asarray(core.next_generation(jnp.asarray(u), jnp.asarray(pop), jnp.asarray(f), jnp.asarray(LB),
                                           jnp.asarray(UB), progress, opts))
    order = np.argsort(f)
    pop_sorted = pop[order]
    u_sel, u_xo, u_mut = _split_draws(u, opts)
    parents = pop_sorted[_hand_pick(_hand_cdf(1.0 / np.sqrt(np.arange(1, P + 1))), u_sel)]
    pa, pb, pm = parents[:n_xo], parents[n_xo:2 * n_xo], parents[2 * n_xo:]
    if crossover == "scattered":
        crossed = np.where(u_xo < 0.5, pa, pb)
    else:
        crossed = np.clip(pa + (1.5 * u_xo - 0.25) * (pb - pa), LB, UB)
    sd = 0.3 * (UB - LB) * (1.0 - 0.5 * progress)
    z = np.vectorize(NormalDist().inv_cdf)(u_mut)
    mutated = np.clip(pm + sd * z, LB, UB)
    np.testing.assert_array_equal(kids[:2], pop_sorted[:2])
    np.testing.assert_allclose(kids[2:2 + n_xo], crossed, rtol=0, atol=1e-15)
    np.testing.assert_allclose(kids[2 + n_xo:], mutated, rtol=0, atol=1e-12)
    assert np.all(kids >= LB) and np.all(kids <= UB)


def test_mutation_spread_shrinks_linearly_to_its_end_value():
    """The same draws at progress 0 and 1 move a mutant by sd0 z and (1 - shrink) sd0 z."""
    opts = core.GAOptions(population=P, elite=0, crossover_fraction=0.0, mutation_scale=0.01, mutation_shrink=0.75)
    pop = np.zeros((P, N))
    f = np.arange(P, dtype=float)
    u = _draws(opts, seed=3)
    args = (jnp.asarray(pop), jnp.asarray(f), jnp.asarray(LB), jnp.asarray(UB))
    start = np.asarray(core.next_generation(jnp.asarray(u), *args, 0.0, opts))
    end = np.asarray(core.next_generation(jnp.asarray(u), *args, 1.0, opts))
    z = np.vectorize(NormalDist().inv_cdf)(_split_draws(u, opts)[2])
    np.testing.assert_allclose(start, 0.01 * (UB - LB) * z, rtol=1e-12)
    np.testing.assert_allclose(end, 0.25 * start, rtol=1e-12)


def test_ring_migration_moves_the_best_of_each_subpopulation_into_the_worst_of_the_next():
    """k = round(fraction P) best of sub-population i (with their costs) replace the k worst of
    sub-population i + 1, and the last one's best go to the first; the rest is untouched."""
    S = 3
    opts = core.GAOptions(population=P, subpopulations=S, migration_fraction=0.2)
    rng = np.random.default_rng(4)
    pops = rng.normal(size=(S, P, N))
    fs = np.stack([rng.permutation(P) + 10.0 * i for i in range(S)]).astype(float)
    new_pops, new_fs = (np.asarray(x) for x in core.migrate(jnp.asarray(pops), jnp.asarray(fs), opts))
    k = 2
    for i in range(S):
        src = (i - 1) % S
        best = np.argsort(fs[src])[:k]
        worst = np.argsort(fs[i])[P - k:]
        np.testing.assert_array_equal(new_pops[i, worst], pops[src, best])
        np.testing.assert_array_equal(new_fs[i, worst], fs[src, best])
        keep = np.setdiff1d(np.arange(P), worst)
        np.testing.assert_array_equal(new_pops[i, keep], pops[i, keep])
        np.testing.assert_array_equal(new_fs[i, keep], fs[i, keep])


def test_seeded_initial_population_is_the_seed_and_a_box_around_it():
    """Seed §5.2.2: individual 0 of every sub-population is the seed (e.g. the linear solution), the
    others are uniform within +-spread x half the bound width of it, clipped to the bounds."""
    opts = core.GAOptions(population=P, subpopulations=2)
    seed_ind = jnp.asarray([0.95, 0.0, -0.1])
    pop = np.asarray(core.initial_population(jax.random.PRNGKey(0), jnp.asarray(LB), jnp.asarray(UB), opts, seed_ind, 0.2))
    half = 0.2 * 0.5 * (UB - LB)
    assert pop.shape == (2, P, N)
    np.testing.assert_array_equal(pop[:, 0], np.broadcast_to(np.asarray(seed_ind), (2, N)))
    assert np.all(pop >= np.maximum(LB, np.asarray(seed_ind) - half)) and np.all(pop <= np.minimum(UB, np.asarray(seed_ind) + half))
    assert np.any(pop[:, 1:, 0] == UB[0])  # the box pokes out of the bound on gene 0 and is clipped there
    random_pop = np.asarray(core.initial_population(jax.random.PRNGKey(0), jnp.asarray(LB), jnp.asarray(UB), opts))
    assert np.all(random_pop >= LB) and np.all(random_pop <= UB)
    assert np.all(random_pop.max(axis=(0, 1)) - random_pop.min(axis=(0, 1)) > 0.5 * (UB - LB))  # spans the box
