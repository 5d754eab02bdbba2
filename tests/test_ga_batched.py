"""Population-wide PRY kinematics and pose fitness (jaxcal.ga.batched) against the per-individual path."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.ga import batched
from jaxcal.ga.fitness import pose_fitness
from jaxcal.robots import pry_robot


def _every_kind_robot():
    """A PRY chain with every joint kind of seed 000 Table 3.3 and non-zero PRY angles."""
    modules = [("revolute", (0.1, 0.02, 0.3), (0.1, -0.2, 0.3)), ("universal", (0.2, 0.0, 0.05), (0.0, 0.3, 0.0)),
               ("cylindrical", (0.0, 0.1, 0.1), (0.2, 0.0, -0.1)), ("spherical", (0.15, -0.05, 0.0), (-0.3, 0.1, 0.2)),
               ("fixed", (0.05, 0.05, 0.05), (0.1, 0.1, 0.1)), ("prismatic", (0.0, 0.0, 0.1), (0.0, 0.4, 0.0))]
    return pry_robot("every-kind", (0.1, -0.2, 0.5), modules)


def _per_individual(rb, dev, a0, free_idx, pop, q, y):
    idx = jnp.asarray(free_idx)
    return jax.jit(jax.vmap(lambda dg: pose_fitness(rb, dev, a0.at[idx].add(dg), q, y, 1.0, 0.7)))(pop)  # compiled whole


@pytest.mark.parametrize("robot", ["mrr1", "every-kind"])
@pytest.mark.parametrize("kind, free_device", [("pose", False), ("pose", True), ("position", True)])
def test_population_fitness_equals_per_individual_fitness(robot, kind, free_device):
    """Same eq 5.4 cost for 40 individuals to 1e-12 relative, with the device frame and marker
    known (scalars) or varied by the GA (per individual), for pose and position readings."""
    rb = jc.robots.get("mrr1") if robot == "mrr1" else _every_kind_robot()
    rng = np.random.default_rng(7)
    dev_true = rng.uniform(-0.05, 0.05, 12 if kind == "pose" else 9)
    q = jc.random_configurations(rb, 8, seed=2)
    data = jc.simulate(rb, rb.nominal + rng.uniform(-0.004, 0.004, rb.n_params), q, kind, device_params=dev_true)
    dev = data.device
    a0 = jnp.concatenate([rb.nominal, jnp.asarray(dev_true) + 0.01])
    n_free = rb.n_params + (dev.n_params if free_device else 0)
    free_idx = tuple(range(n_free))
    assert batched.supports(rb, dev)
    pop = jnp.asarray(rng.uniform(-0.005, 0.005, (40, n_free)))
    qj, y = jnp.asarray(data.q), jnp.asarray(data.y)
    fast = batched.population_fitness(rb, dev, a0, free_idx, pop, qj, y, 1.0, 0.7)
    ref = _per_individual(rb, dev, a0, free_idx, pop, qj, y)
    assert fast.shape == (40,)
    assert np.max(np.abs(fast - ref) / ref) < 1e-12
    # leading axes (sub-populations) are kept
    assert batched.population_fitness(rb, dev, a0, free_idx, pop.reshape(4, 10, -1), qj, y, 1.0, 0.7).shape == (4, 10)


def test_population_fitness_gradient_matches_central_differences():
    """jacfwd of the population cost w.r.t. one individual vs central FD (h = 1e-6): rel. err < 1e-6."""
    from conftest import central_fd, rel_err

    rb = jc.robots.get("mrr1")
    data = jc.simulate(rb, rb.nominal + 0.003, jc.random_configurations(rb, 8, seed=4), "pose")
    a0 = jnp.concatenate([rb.nominal, data.device.nominal])
    free_idx = tuple(range(rb.n_params))
    q, y = jnp.asarray(data.q), jnp.asarray(data.y)
    f = jax.jit(lambda dg: batched.population_fitness(rb, data.device, a0, free_idx, dg[None], q, y))
    x = jnp.asarray(np.random.default_rng(0).uniform(-0.002, 0.002, rb.n_params))
    assert rel_err(jax.jacfwd(f)(x), central_fd(f, x)) < 1e-6


def test_supports_only_pry_chains_with_pose_or_position_readings():
    """Other robots/devices take the per-individual vmapped path (e.g. the self-calibration GA)."""
    mrr1, stanford = jc.robots.get("mrr1"), jc.robots.get("stanford")
    assert batched.supports(mrr1, jc.measure.make_device("tracker"))
    assert not batched.supports(stanford, jc.measure.make_device("pose"))  # MDH with gains
    assert not batched.supports(mrr1, jc.measure.make_device("three_point"))
