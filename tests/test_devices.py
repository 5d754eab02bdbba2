"""Device classes: weights per residual component, the noise model (same draws as before the
classes, eager and under jit), Monte Carlo for every noise model, and a device added in one file
(this one): a planar position sensor that reads (x, y) only, simulated and identified end to end."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.fit import uncertainty as un
from jaxcal.kin.rotations import exp_so3
from jaxcal.measure import key_normal, register, registered_kinds
from jaxcal.measure.base import FRAME_INDEX, XYZ, Device, additive_noise, frame_from_params, frame_names

SP, SR = 2e-4, 3e-3  # position (m) and orientation (rad) noise


class PlanarPosition(Device):
    """Worked example of a new device: a 2-D sensor (a camera looking along its z axis, in metres on
    its image plane) that reads the (x, y) of one marker point in its frame, y = (D^-1 T_tip m)_xy."""

    kind = "planar_position"
    residual_components = ("length", "length")
    frame_index = FRAME_INDEX

    @classmethod
    def build(cls) -> "PlanarPosition":
        return cls.nominal_device(frame_names("dev") + frame_names("tool", XYZ), (2,))

    def read(self, tip, d):
        """(D^-1 T_tip m)[:2] with D = frame(d[0:6]), m = d[6:9]."""
        return frame_from_params(d[0:6]).inverse().apply(tip.apply(d[6:9]))[:2]

    def residual(self, pred, meas):
        """y_meas - y_pred (2,)."""
        return meas - pred

    def split_errors(self, res):
        """(|r| per sample, None)."""
        return jnp.linalg.norm(res, axis=-1), None

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_position n, n (N, 2)."""
        return additive_noise(y, normal, sigma_position)


register(PlanarPosition, "planar")

OPTIONS = {"multi_position": {"points": 2}}


def _device(kind):
    return jc.make_device(kind, **OPTIONS.get(kind, {}))


def _exact(robot, device, n=6, seed=0):
    """Noise-free readings of `device` (nominal frame moved off the robot) at n configurations."""
    q = jc.random_configurations(robot, n, seed=seed)
    d = np.asarray(device.nominal_np).copy()
    d[: min(3, len(d))] += [1.5, -0.4, 0.3][: min(3, len(d))]
    y = jc.simulate(robot, robot.nominal, q, device, device_params=d).y
    return q, d, y


def _two_tip_tree():
    """TALOS read at both hands: what a device reading two links (link_camera) needs."""
    import os

    from jaxcal.robots.real_datasets import DATA_DIR

    return jc.load_robot(os.path.join(DATA_DIR, "talos", "talos.urdf"), base="base_link",
                         tips=["arm_left_7_link", "arm_right_7_link"])


@pytest.mark.parametrize("kind", registered_kinds())
def test_weights_follow_the_residual_components(kind):
    dev = _device(kind)
    rb = _two_tip_tree() if kind == "link_camera" else jc.robots.get("stanford")
    _, _, y = _exact(rb, dev, n=1)
    res = dev.residual(jnp.asarray(y[0]), jnp.asarray(y[0]))
    w = np.asarray(dev.weights(SP, SR))
    assert w.shape == res.shape == (len(dev.residual_components),)
    expect = [1 / SP if c == "length" else 1 / SR for c in dev.residual_components]
    np.testing.assert_array_equal(w, expect)
    np.testing.assert_array_equal(jc.fit.residual_weights(dev, SP, SR), w)
    assert dev.error_unit == ("mm" if "length" in dev.residual_components else "mrad")


def _old_noise(kind, y, rng):
    """The per-kind noise of `simulate` before the device classes, inline."""
    y = np.array(y)
    if kind in ("position", "three_point", "multi_position", "laser_range"):
        return y + SP * rng.standard_normal(y.shape)
    if kind == "pose":
        y[:, :3, 3] += SP * rng.standard_normal((len(y), 3))
        dR = np.asarray(jax.vmap(exp_so3)(jnp.asarray(SR * rng.standard_normal((len(y), 3)))))
        y[:, :3, :3] = dR @ y[:, :3, :3]
        return y
    if kind == "theodolite":
        return y + SR * rng.standard_normal(y.shape)
    dR = np.asarray(jax.vmap(exp_so3)(jnp.asarray(SR * rng.standard_normal((len(y), 3)))))
    return dR @ y


@pytest.mark.parametrize("kind", ["position", "multi_position", "pose", "orientation", "three_point", "theodolite",
                                  "laser_range"])
def test_simulate_draws_the_same_noise_as_before(kind):
    rb = jc.robots.get("stanford")
    dev = _device(kind)
    q, d, y = _exact(rb, dev)
    noisy = jc.simulate(rb, rb.nominal, q, dev, noise={"position": SP, "orientation": SR}, device_params=d, seed=5)
    rng = np.random.default_rng(5)
    rng.standard_normal(q.shape)  # simulate's actuator draw comes first
    expect = _old_noise(kind, y, rng)
    assert not np.allclose(noisy.y, y)
    # the same draws: a different draw moves readings by ~SP or SR (1e-3 here); the rotated readings (pose,
    # orientation) are products dR R, which numpy and XLA may sum in another order (1 ulp: XLA's LLVM level 0
    # in the tests gives 1.1e-16 on 7 of 96 entries), so those agree to a few ulp, the others exactly
    np.testing.assert_allclose(noisy.y, expect, rtol=0, atol=1e-15 if kind in ("pose", "orientation") else 0)


@pytest.mark.parametrize("kind", ["position", "pose", "theodolite", "orientation"])
def test_add_noise_under_jit_with_keys(kind):
    rb = jc.robots.get("stanford")
    dev = _device(kind)
    _, _, y = _exact(rb, dev)
    key = jax.random.PRNGKey(3)
    jitted = jax.jit(lambda y, k: dev.add_noise(y, key_normal(k), SP, SR))(jnp.asarray(y), key)
    eager = dev.add_noise(jnp.asarray(y), key_normal(key), SP, SR)
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-14)
    res = jax.vmap(dev.residual)(jnp.asarray(y), jitted)
    comp = np.array(dev.residual_components)
    for c, s in (("length", SP), ("angle", SR)):
        if (comp == c).any():  # the noise is of the stated size on each component kind
            rms = float(jnp.sqrt(jnp.mean(res[:, comp == c] ** 2)))
            assert 0.2 * s < rms < 3 * s


@pytest.mark.parametrize("kind, noise", [("theodolite", {"orientation": 1e-5}), ("laser_range", {"position": 1e-5})])
def test_monte_carlo_runs_for_angle_and_range_devices(kind, noise):
    """Monte Carlo drew pose-like rotation noise for these devices (a shape error) before `add_noise`."""
    rb = jc.robots.get("mrr1")
    a = jc.perturb(rb, 1e-3, seed=1)
    q = jc.random_configurations(rb, 12, seed=2)
    dev = _device(kind).with_values(**{"dev.x": 1.5, "dev.y": -0.4, "dev.z": 0.3})
    mc = un.monte_carlo(rb, a, q, dev, noise=noise, runs=4, chunk=4, known=("dev",), devices=[], max_steps=10,
                        sigma_position=1e-5, sigma_orientation=1e-5)
    assert mc.estimates.shape[0] == 4 and np.isfinite(mc.estimates).all()
    assert np.std(mc.estimates, axis=0).max() > 0  # the runs saw different noise


def test_a_device_in_one_file_simulates_and_identifies():
    """PlanarPosition above, registered in this file only: simulate and identify on the Stanford arm."""
    rb = jc.robots.get("stanford")
    a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=8)
    dev = jc.make_device("planar").with_values(**{"dev.z": -1.0})
    assert jc.measure.as_device("planar_position") == jc.make_device("planar_position")
    q = jc.random_configurations(rb, 120, seed=1)
    sigma = 1e-5
    data = jc.simulate(rb, a_true, q, dev, noise={"position": sigma}, seed=2)
    assert data.y.shape == (120, 2)
    fit = jc.identify(rb, data, known=("dev",), sigma_position=sigma)
    floor = np.sqrt(2) * sigma * 1e3  # RMS of the 2-D noise vector, mm
    assert fit.rms_before > 20 * floor and fit.rms_after < 1.5 * floor
    assert "planar_position samples" in fit.report() and " mm " in fit.report()
