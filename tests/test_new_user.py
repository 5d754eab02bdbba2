"""A new user's first calibration: a URDF and a CSV in a folder, `jaxcal calibrate`, a report and a
calibrated URDF back, and that URDF predicts poses it never saw better than the nominal one."""

import json

import jax.numpy as jnp
import numpy as np

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.measure.devices import frame_from_params

ARM_URDF = """<?xml version="1.0"?>
<robot name="arm4">
  <link name="base_link"/>
  <link name="link1"/><link name="link2"/><link name="link3"/><link name="link4"/><link name="tool"/>
  <joint name="shoulder_pan" type="revolute">
    <parent link="base_link"/><child link="link1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2.8" upper="2.8" effort="10" velocity="1"/>
  </joint>
  <joint name="shoulder_lift" type="revolute">
    <parent link="link1"/><child link="link2"/>
    <origin xyz="0 0.05 0.1" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-1.8" upper="1.8" effort="10" velocity="1"/>
  </joint>
  <joint name="elbow" type="revolute">
    <parent link="link2"/><child link="link3"/>
    <origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2.5" upper="2.5" effort="10" velocity="1"/>
  </joint>
  <joint name="wrist" type="revolute">
    <parent link="link3"/><child link="link4"/>
    <origin xyz="0.35 0 0" rpy="0 0.3 0"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/>
  </joint>
  <joint name="tool_mount" type="fixed">
    <parent link="link4"/><child link="tool"/>
    <origin xyz="0.12 0 0.02" rpy="0 0 0"/>
  </joint>
</robot>
"""
DEVICE_TRUE = np.array([0.8, -0.3, 0.05, 0.02, -0.03, 1.2,  # tracker frame in the robot base (m, rotation vector)
                        0.03, 0.01, 0.02])  # marker on the tool link (m)


def _predict(robot, a, d, q):
    """Tracker readings of the model (robot a, device d): D^-1 T_tip(q) m."""
    tips = jc.forward(robot, jnp.asarray(a), jnp.asarray(q))
    D = frame_from_params(jnp.asarray(d[:6]))
    return np.asarray(D.inverse().apply(tips.apply(jnp.asarray(d[6:9]))))


def test_urdf_and_csv_to_calibrated_urdf(tmp_path):
    urdf = tmp_path / "arm4.urdf"
    urdf.write_text(ARM_URDF)
    rb = jc.load_robot(str(urdf), base="base_link", tip="tool")
    a_true = jc.perturb(rb, {"length": 1.5e-3, "angle": 3e-3}, seed=4)
    q = jc.random_configurations(rb, 60, seed=5, margin=0.05)
    data = jc.simulate(rb, a_true, q, "position", noise=2e-5, device_params=DEVICE_TRUE, seed=6)
    csv = data.to_csv(tmp_path / "tracker.csv", length_unit="mm", angle_unit="deg")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    out = tmp_path / "result"
    rc = main(["calibrate", str(urdf), csv, "--base", "base_link", "--tip", "tool", "--out", str(out),
               "--sigma-position", "2e-5", "-q"])
    assert rc == 0
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before  # inputs untouched
    res = json.load(open(out / "results.json"))
    assert (out / "report.md").exists() and (out / "error_map.png").stat().st_size > 10_000
    held = res["rms"]["heldout"]["position_mm"]
    assert held["after"] < 0.1 * held["before"], held

    # the calibrated URDF, re-imported, predicts 40 new poses better than the nominal URDF
    cal = jc.load_robot(str(out / "arm4_calibrated.urdf"), base="base_link", tip="tool")
    q_new = jc.random_configurations(rb, 40, seed=7, margin=0.05)
    truth = _predict(rb, a_true, DEVICE_TRUE, q_new)
    dev = res["device_params"]
    d_cal = np.array([dev["calibrated"][n] for n in data.device.names])
    d_nom = np.array([dev["nominal_robot"][n] for n in data.device.names])
    err_cal = np.linalg.norm(_predict(cal, cal.nominal, d_cal, q_new) - truth, axis=1)
    err_nom = np.linalg.norm(_predict(rb, rb.nominal, d_nom, q_new) - truth, axis=1)
    rms_cal, rms_nom = (float(np.sqrt(np.mean(e**2))) * 1e3 for e in (err_cal, err_nom))
    # errors of 1.5 mm / 3 mrad give a few mm; 0.02 mm noise: the calibrated model is within 0.1 mm
    print(f"new poses: nominal URDF {rms_nom:.4g} mm, calibrated URDF {rms_cal:.4g} mm; fit {res['timings_s']}")
    assert rms_cal < 0.1 < 1.0 < rms_nom, (rms_cal, rms_nom)
