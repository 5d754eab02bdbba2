"""Multi-marker position device ("multi_position"): K points on the tool, each with its own
identified offset, read together in one device frame."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.fit.data import DataError
from jaxcal.fit.identify import residual_weights, residuals

OFFSETS = np.array([[0.05, 0.0, 0.02], [-0.03, 0.06, 0.01], [0.0, -0.04, 0.08]])  # three points on the tool, m
FRAME = np.array([0.8, -0.5, 0.3, 0.1, -0.2, 0.7])  # device frame in the robot base (m, rotation vector)


def _device_params(dev):
    return jnp.concatenate([jnp.asarray(FRAME), jnp.asarray(OFFSETS).ravel()])


def test_reads_every_point_in_the_device_frame():
    dev = jc.make_device("multi_position", points=3)
    assert dev.reading_shape == (3, 3) and dev.n_params == 15 and dev.names[6:9] == ("tool.p1.x", "tool.p1.y", "tool.p1.z")
    assert jc.make_device("markers", points=2).kind == "multi_position"
    tip = jc.Pose(jnp.asarray(jc.measure.devices.exp_so3(jnp.array([0.3, 0.1, -0.2]))), jnp.array([0.4, 0.2, 0.9]))
    d = _device_params(dev)
    y = dev.read(tip, d)
    single = jc.make_device("position")
    for k in range(3):  # point k is what a one-point device with marker k reads
        assert np.allclose(y[k], single.read(tip, jnp.concatenate([d[:6], d[6 + 3 * k:9 + 3 * k]])), atol=1e-15)
    # per-sample position error: RMS over the points of the 3-D error
    res = jnp.array([[3.0, 0, 0, 0, 4.0, 0, 0, 0, 0]])
    two = jc.make_device("multi_position", points=3).split_errors(res)[0]
    assert np.isclose(float(two[0]), np.sqrt(25.0 / 3))
    with pytest.raises(ValueError, match="points=K"):
        jc.make_device("multi_position")
    with pytest.raises(ValueError, match="points= is for"):
        jc.make_device("position", points=2)


def test_jacobian_matches_central_differences():
    """jacfwd of the weighted residuals w.r.t. robot + device parameters (Stanford arm, 3 points)
    vs central differences, h = 1e-6: relative error < 1e-7 (measured 1.3e-10)."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device("multi_position", points=3)
    q = jnp.asarray(jc.random_configurations(rb, 5, seed=1, margin=0.2))
    a_full = jnp.concatenate([jc.perturb(rb, 1e-3, seed=2), _device_params(dev)])
    y = jax.vmap(dev.read, (0, None))(jc.forward(rb, a_full[:rb.n_params], q), a_full[rb.n_params:]) + 1e-3
    w = residual_weights(dev, 1e-3)
    assert w.shape == (9,)

    def f(x):
        return residuals(rb, dev, x, q, y, w).ravel()

    rel = rel_err(jax.jacfwd(f)(a_full), central_fd(f, a_full, h=1e-6))
    assert rel < 1e-7, rel


def test_identify_recovers_every_point_offset_and_the_device_frame():
    """Simulated Stanford arm, 3 markers, 0.05 mm noise: with the robot known, identify finds the
    device frame and the three offsets to 0.05 mm (start: all zero); with the robot geometry free
    too, the fit reaches the noise floor and the distances between the points (which no robot
    parameter can absorb: the last link's parameters move and turn all points together) come back to 0.02 mm."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device("multi_position", points=3)
    a_true = jc.perturb(rb, 2e-3, seed=3)
    q = jc.random_configurations(rb, 40, seed=4, margin=0.1)
    data = jc.simulate(rb, a_true, q, device=dev, noise=5e-5, device_params=_device_params(dev), seed=5)
    assert data.y.shape == (40, 3, 3)

    known = jc.identify(rb, data, free=(), a0=a_true)
    # RMS of the 3-D point error at the noise floor: 0.05 mm x sqrt(3) = 0.087 mm less 15 fitted of 360 residuals
    assert 0.075 < known.rms_after < 0.09
    assert np.max(np.abs(np.asarray(known.device_params[6:]).reshape(3, 3) - OFFSETS)) < 5e-5
    assert np.max(np.abs(np.asarray(known.device_params[:3]) - FRAME[:3])) < 5e-5

    full = jc.identify(rb, data)
    assert full.rms_before > 1.0 and full.rms_after < 0.09
    pts = np.asarray(full.device_params[6:]).reshape(3, 3)
    distances = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)  # noqa: E731
    assert np.max(np.abs(distances(pts) - distances(OFFSETS))) < 2e-5


def test_csv_reads_the_markers_together(tmp_path):
    rb = jc.robots.get("stanford")
    dev = jc.make_device("multi_position", points=3)
    q = jc.random_configurations(rb, 4, seed=6)
    data = jc.simulate(rb, rb.nominal, q, device=dev, device_params=_device_params(dev))
    cols = ",".join(f"{a}{k}" for k in (1, 2, 3) for a in "xyz")
    q_file = q * np.array([1, 1, 1e3, 1, 1, 1])  # j3 is prismatic: in the file's length unit, mm
    rows = [",".join(f"{v:.17g}" for v in np.concatenate([data.y[i].ravel() * 1e3, q_file[i]])) for i in range(4)]
    path = tmp_path / "markers.csv"
    path.write_text("# units: length=mm\n" + cols + "," + ",".join(rb.joint_names) + "\n" + "\n".join(rows) + "\n")
    every = jc.Dataset.from_csv(path, device="multi_position", prismatic=jc.fit.csvfile.prismatic_joints(rb))
    assert every.device.reading_shape == (3, 3) and np.allclose(every.y, data.y, atol=1e-15)
    assert np.allclose(every.q, q)
    two = jc.Dataset.from_csv(path, device="markers", marker=(1, 3), prismatic=jc.fit.csvfile.prismatic_joints(rb))
    assert np.allclose(two.y, data.y[:, [0, 2]], atol=1e-15)
    with pytest.raises(DataError, match=r"marker\(s\) \['4'\] not found"):
        jc.Dataset.from_csv(path, device="multi_position", marker=(1, 4))
    with pytest.raises(DataError, match=r"shape \(N, K points, 3\)"):
        jc.Dataset(q=q, y=data.y[:, 0], device="multi_position")
