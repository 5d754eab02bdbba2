"""Theodolite and laser-range devices (seed 004 §4.2-4.4): readings, gradients, theodolite location
from a reference tree, simulation through the Delta closure, and identification through closure."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.closure import delta as dl
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.measure.devices import frame_from_params, locate_theodolite


def test_theodolite_reads_azimuth_and_elevation():
    dev = jc.make_device("theodolite")
    d = dev.nominal.at[6:9].set(0.0)
    tip = jc.Pose(jnp.eye(3), jnp.array([1.0, 1.0, np.sqrt(2.0)]))
    az, el = dev.read(tip, d)
    assert abs(float(az) - np.pi / 4) < 1e-15 and abs(float(el) - np.pi / 4) < 1e-15
    # the residual wraps the azimuth across +-pi
    r = dev.residual(jnp.array([np.pi - 1e-3, 0.0]), jnp.array([-np.pi + 1e-3, 0.0]))
    assert abs(float(r[0]) - 2e-3) < 1e-12


def test_laser_range_reads_distance():
    dev = jc.make_device("laser_range")
    d = jnp.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.1])
    tip = jc.Pose(jnp.eye(3), jnp.array([1.0, 2.0, 0.0]))
    assert abs(float(dev.read(tip, d)[0]) - 2.9) < 1e-15
    assert dev.reading_shape == (1,) and jc.make_device("laser").kind == "laser_range"
    assert jc.make_device("inclinometer").kind == "orientation"


@pytest.mark.parametrize("kind", ["theodolite", "laser_range"])
def test_device_jacobian_matches_central_differences(kind):
    """jacfwd of the residuals w.r.t. robot + device parameters (Stanford arm, open chain) vs
    central differences with h = 1e-6: relative error < 1e-7."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device(kind)
    d = jnp.asarray(dev.nominal_np)
    if kind == "theodolite":
        d = d.at[0:6].set(jnp.array([-1.2, -3.4, -0.16, 0.1, -0.05, 1.4])).at[6:9].set(jnp.array([0.01, 0.02, 0.05]))
    else:
        d = d.at[0:3].set(jnp.array([-1.2, -3.4, -0.16])).at[3:6].set(jnp.array([0.01, 0.02, 0.05]))
    q = jnp.asarray(jc.random_configurations(rb, 6, seed=1, margin=0.2))
    a_full = jnp.concatenate([jc.perturb(rb, 1e-3, seed=2), d])
    y = jax.vmap(dev.read, (0, None))(jc.forward(rb, a_full[:rb.n_params], q), d) + 1e-3
    w = residual_weights(dev, 1.0, 1.0)

    def f(x):
        return residuals(rb, dev, x, q, y, w).ravel()

    J = jax.jacfwd(f)(a_full)
    h = 1e-6
    J_fd = np.stack([(f(a_full.at[i].add(h)) - f(a_full.at[i].add(-h))) / (2 * h) for i in range(len(a_full))], 1)
    rel = np.linalg.norm(J - J_fd) / np.linalg.norm(J_fd)
    assert rel < 1e-7, rel


def test_locate_theodolite_from_reference_tree():
    """Three known tree points read as (azimuth, elevation) locate the instrument (§4.4.3); the
    thesis found it at (-1.2197, -3.4359, -0.1611) m."""
    truth = jnp.array([-1.2197, -3.4359, -0.1611, 0.02, -0.01, 1.25])
    tree = jnp.array([[0.0, 0.0, 0.3], [0.2, 0.0, 0.45], [0.0, 0.2, 0.6]])
    D = frame_from_params(truth).inverse()
    readings = jax.vmap(lambda p: jc.measure.devices.sight_angles(D.apply(p)))(tree)
    est, rms = locate_theodolite(tree, readings, start=truth + jnp.array([0.1, 0.2, -0.1, 0.02, 0.02, 0.1]))
    assert rms < 1e-12 and float(jnp.max(jnp.abs(est - truth))) < 1e-8
    with pytest.raises(ValueError, match="readings must be"):
        locate_theodolite(tree, readings[:2])


def test_simulate_theodolite_and_range_through_delta_closure():
    rb = jc.robots.get("delta")
    theta, _ = jax.jit(jax.vmap(dl.inverse))(jnp.asarray(dl.grid()[:16]))
    dev = jc.make_device("theodolite").with_values(**{"dev.x": -1.2197, "dev.y": -3.4359, "dev.z": -0.1611, "dev.rz": 1.3})
    a = dl.full_precision_nominal(rb)
    data = jc.simulate(rb, a, np.asarray(theta), dev)
    P, _ = jax.jit(jax.vmap(dl.direct))(theta)
    v = (P - jnp.array([-1.2197, -3.4359, -0.1611])) @ frame_from_params(dev.nominal).R
    assert data.y.shape == (16, 2)
    assert float(jnp.max(jnp.abs(jnp.arctan2(v[:, 1], v[:, 0]) - data.y[:, 0]))) < 1e-12
    assert float(jnp.max(jnp.abs(jnp.arctan2(v[:, 2], jnp.hypot(v[:, 0], v[:, 1])) - data.y[:, 1]))) < 1e-12
    rng = jc.simulate(rb, a, np.asarray(theta), "laser_range")
    assert float(jnp.max(jnp.abs(rng.y[:, 0] - jnp.linalg.norm(P, axis=-1)))) < 1e-12
