"""The theodolite with a built-in laser range finder (seed 004 §4.4.2): readings, residual, noise,
gradient through the residuals, and identification of a serial robot with the instrument frame unknown."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.measure.theodolite_range import TheodoliteRange, sight_vector

D_TRUE = np.array([1.5, -0.4, 0.3, 0.05, -0.1, 2.2, 0.01, 0.02, 0.05])  # instrument frame (6), marker (3)
SIGMA_ANGLE, SIGMA_RANGE = 1e-5, 1e-4  # rad (2 seconds of arc), m


def test_reads_azimuth_elevation_and_range():
    dev = jc.make_device("theodolite_range")
    assert isinstance(dev, TheodoliteRange) and jc.make_device("total_station") == dev
    tip = jc.Pose(jnp.eye(3), jnp.array([1.0, 1.0, np.sqrt(2.0)]))
    y = dev.read(tip, dev.nominal)
    np.testing.assert_allclose(y, [np.pi / 4, np.pi / 4, 2.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(dev.points(y[None])[0, 0], tip.p, rtol=0, atol=1e-15)
    # the azimuth wraps at +-pi, the range does not
    r = dev.residual(jnp.array([np.pi - 1e-3, 0.1, 2.0]), jnp.array([-np.pi + 1e-3, 0.1, 2.5]))
    np.testing.assert_allclose(r, [2e-3, 0.0, 0.5], rtol=0, atol=1e-12)
    assert dev.residual_components == ("angle", "angle", "length")
    np.testing.assert_allclose(dev.weights(1e-4, 1e-5), [1e5, 1e5, 1e4], rtol=1e-15)


def test_noise_goes_to_angles_and_range_by_kind():
    dev = jc.make_device("theodolite_range")
    y = jnp.tile(jnp.array([0.3, -0.2, 2.0]), (4000, 1))
    noisy = dev.add_noise(y, np.random.default_rng(0).standard_normal, SIGMA_RANGE, SIGMA_ANGLE)
    std = np.std(np.asarray(noisy - y), axis=0)
    np.testing.assert_allclose(std, [SIGMA_ANGLE, SIGMA_ANGLE, SIGMA_RANGE], rtol=0.05)
    pos, ang = dev.split_errors(jnp.array([[3e-5, 4e-5, -2e-3]]))
    assert abs(float(pos[0]) - 2e-3) < 1e-15 and abs(float(ang[0]) - 5e-5) < 1e-15


def test_readings_back_to_points():
    y = jnp.asarray(np.random.default_rng(1).uniform([-np.pi, -1.4, 0.5], [np.pi, 1.4, 4.0], (50, 3)))
    dev = jc.make_device("theodolite_range")
    back = jax.vmap(lambda v: dev.read(jc.Pose(jnp.eye(3), v), dev.nominal))(sight_vector(y))
    assert float(jnp.max(jnp.abs(back - y))) < 1e-14


def test_gradient_matches_central_differences():
    """jacfwd of the weighted residuals w.r.t. robot + device parameters (Stanford arm) vs central
    differences, h = 1e-6, float64: relative error ~1e-10 (bound 1e-8)."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device("theodolite_range")
    q = jnp.asarray(jc.random_configurations(rb, 6, seed=1, margin=0.2))
    a_full = jnp.concatenate([jc.perturb(rb, 1e-3, seed=2), jnp.asarray(D_TRUE)])
    y = jax.vmap(dev.read, (0, None))(jc.forward(rb, a_full[: rb.n_params], q), jnp.asarray(D_TRUE)) + 1e-3
    w = residual_weights(dev, 1.0, 1.0)

    def f(x):
        return residuals(rb, dev, x, q, y, w).ravel()

    J = jax.jacfwd(f)(a_full)
    assert rel_err(J, central_fd(f, a_full, h=1e-6)) < 1e-8


@pytest.fixture(scope="module")
def study():
    """Stanford arm, 60 settings, instrument frame and marker unknown (started by registering the
    readings as points): noise-free with every free parameter perturbed by 1 mm / 1 mrad."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device("theodolite_range")
    q = jc.random_configurations(rb, 60, seed=3, margin=0.2)
    a_true = jc.perturb(rb, 1e-3, seed=4)
    data = jc.simulate(rb, a_true, q, dev, device_params=D_TRUE)
    fit = jc.identify(rb, data, sigma_position=SIGMA_RANGE, sigma_orientation=SIGMA_ANGLE)
    return rb, dev, q, a_true, fit


def _marker(rb, a, d, q):
    return jc.forward(rb, a, q).apply(jnp.asarray(d)[6:9])


def test_identify_noise_free_round_trip(study):
    """Noise-free: the readings fit to rounding, the device frame is recovered and the calibrated model
    places the marker like the true robot at 40 new settings (1e-9 m)."""
    rb, dev, _, a_true, fit = study
    assert fit.rms_after < 1e-6  # mm
    np.testing.assert_allclose(fit.device_params[:3], D_TRUE[:3], rtol=0, atol=1e-2)  # frame vs robot base: see docs
    q_new = jc.random_configurations(rb, 40, seed=9, margin=0.2)
    frame_fit = jc.measure.frame_from_params(fit.device_params[:6])
    frame_true = jc.measure.frame_from_params(jnp.asarray(D_TRUE[:6]))
    # compare in the instrument frame (the base frame itself trades off against the instrument frame)
    seen_fit = frame_fit.inverse().apply(_marker(rb, fit.a, fit.device_params, q_new))
    seen_true = frame_true.inverse().apply(_marker(rb, a_true, D_TRUE, q_new))
    assert float(jnp.max(jnp.abs(seen_fit - seen_true))) < 1e-9


def test_identify_with_noise_within_standard_errors(study):
    """Truth perturbed on the estimated parameters only (the others kept, so the estimates are comparable
    with it); angle noise 1e-5 rad, range noise 1e-4 m: every estimate within 4.5 standard errors
    (31 estimated, measured |z| <= 2.4)."""
    rb, dev, q, _, fit0 = study
    names = [n for n in fit0.estimated if n in rb.names]
    delta = np.random.default_rng(5).normal(0.0, 1e-3, len(names))
    a_true = np.asarray(rb.nominal).copy()
    a_true[[rb.index(n) for n in names]] += delta
    d_true = np.asarray(fit0.device_params)  # the frame as the noise-free fit split it from the robot
    data = jc.simulate(rb, a_true, q, dev, device_params=d_true, noise={"position": SIGMA_RANGE, "orientation": SIGMA_ANGLE},
                       seed=6)
    fit = jc.identify(rb, data, sigma_position=SIGMA_RANGE, sigma_orientation=SIGMA_ANGLE)
    full_true = np.concatenate([a_true, d_true])
    se = fit.std_errors
    est = np.concatenate([np.asarray(fit.a), np.asarray(fit.device_params)])
    z = [(est[fit.names.index(n)] - full_true[fit.names.index(n)]) / se[n] for n in fit.estimated]
    assert len(z) >= 20 and max(abs(v) for v in z) < 4.5, sorted(z)
    assert 0.5 < float(np.sqrt(np.mean(np.square(z)))) < 2.0  # the standard errors are of the right size (1.04 measured)
