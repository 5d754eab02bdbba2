"""Calibration exports for ROS robots loaded from a URDF: a URDF with `<calibration rising>` tags and
PAL Robotics' calibration YAML.

URDF with rising tags (`rising_urdf_text`): each joint read by an encoder (moving, not a `<mimic>`)
gets a `<calibration rising="offset"/>` child holding its identified offset (rad, or m for a prismatic
joint); every other identified quantity goes into the joint origins as in `jaxcal.robots.urdf.urdf_text`.
A reader that applies the tags adds them to the joint readings: q_model = q_reading + rising reproduces
the calibrated tool pose. A mimic joint has no reading of its own: its origin holds its offset less what
its source's rising value adds through the mimic multiplier.

PAL YAML (`pal_calibration`): the flat mapping PAL's TIAGo description reads as calibration
properties, as FIGAROH writes it for TIAGo: `camera_position_x|y|z` and `camera_orientation_r|p|y` (the
device frame in the robot base frame, URDF roll-pitch-yaw), `<joint>_offset` per moving joint (the
joint's zero correction) and `tip_position_x|y|z` (the marker on the tool link; `tip_orientation_r|p|y`
too for pose devices). It holds joint offsets only: the other geometry jaxcal identifies is in the URDF
exports (a comment at the top of the file says so).
"""

from __future__ import annotations

import numpy as np

from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.urdf import matrix_rpy, urdf_text

RISING_TAG = "calibration"
EXPORT_KINDS = ("urdf-rising", "pal-yaml")


def _require_urdf(robot, what: str) -> None:
    if "urdf_bodies" not in robot.extras:
        raise RobotFileError(f"{what} needs a robot loaded from a URDF; {robot.name!r} was not")


def _moving(robot):
    """(URDF joint name, body) of each moving body of the chain."""
    return [(meta["joint"], body) for body, meta in zip(robot.bodies, robot.extras["urdf_bodies"]) if body.kind[0] != "fixed"]


def encoder_joints(robot) -> dict[str, int]:
    """URDF joint name -> index of its offset parameter, for every joint of the chain read by an encoder (the
    robot's inputs; a `<mimic>` joint is none)."""
    _require_urdf(robot, "the rising-tag export")
    offsets = {name: body.rows[6] for name, body in _moving(robot)}
    return {name: offsets[name] for name in robot.joint_names if name in offsets}


def rising_values(robot, a) -> dict[str, float]:
    """The `<calibration rising>` value of each encoder joint at parameters `a`: its offset."""
    a = np.asarray(a, float)
    return {name: float(a[i]) for name, i in encoder_joints(robot).items()}


def rising_urdf_text(robot, a) -> str:
    """The source URDF with identified geometry in the origins and the encoder joints' offsets in
    `<calibration rising=.../>` children (module docstring); any earlier `<calibration>` is replaced.
    A mimic joint's origin takes its offset less what the rising values of its sources add through the coupling."""
    from lxml import etree

    a = np.asarray(a, float)
    rising = rising_values(robot, a)
    r = np.array([rising.get(name, 0.0) for name in robot.joint_names])
    C = np.eye(len(r)) if robot.coupling_joint is None else np.asarray(robot.coupling_joint, float)
    added = C @ r  # per joint variable: what the readings plus rising values add to it
    a0 = a.copy()
    for _, body in _moving(robot):
        a0[body.rows[6]] = a[body.rows[6]] - added[body.inputs[0]]
    root = etree.fromstring(urdf_text(robot, a0).encode())
    for joint in root.findall("joint"):
        if joint.get("name") in rising:
            for old in joint.findall(RISING_TAG):
                joint.remove(old)
            etree.SubElement(joint, RISING_TAG).set("rising", f"{rising[joint.get('name')]:.17g}")
    root.insert(0, etree.Comment(" <calibration rising> holds each encoder joint's identified offset: "
                                 "joint value = reading + rising "))
    return etree.tostring(root, xml_declaration=True, encoding="utf-8").decode()


def read_rising(text: str) -> dict[str, float]:
    """Joint name -> `rising` value of every `<calibration rising>` tag of a URDF text."""
    from lxml import etree

    root = etree.fromstring(text.encode())
    return {j.get("name"): float(c.get("rising")) for j in root.findall("joint")
            for c in j.findall(RISING_TAG) if c.get("rising") is not None}


def _rotvec_rpy(v) -> list[float]:
    from scipy.spatial.transform import Rotation

    return [float(x) for x in matrix_rpy(Rotation.from_rotvec(np.asarray(v, float)).as_matrix())]


def pal_calibration(robot, a, device_params: dict) -> dict:
    """PAL's flat calibration mapping (module docstring) from robot parameters `a` and the device parameters
    {"dev.x": ..., "tool.x": ...} of a fit; entries whose quantities the device does not have are left out."""
    _require_urdf(robot, "the PAL calibration YAML export")
    a = np.asarray(a, float)
    out = {}
    dev = [device_params.get(f"dev.{k}") for k in ("x", "y", "z", "rx", "ry", "rz")]
    if None not in dev:
        out.update(zip(("camera_position_x", "camera_position_y", "camera_position_z"), map(float, dev[:3])))
        out.update(zip(("camera_orientation_r", "camera_orientation_p", "camera_orientation_y"), _rotvec_rpy(dev[3:])))
    for body, meta in zip(robot.bodies, robot.extras["urdf_bodies"]):
        if body.kind[0] != "fixed":
            out[f"{meta['joint']}_offset"] = float(a[body.rows[6]])
    tip = [device_params.get(f"tool.{k}") for k in ("x", "y", "z")]
    if None not in tip:
        out.update(zip(("tip_position_x", "tip_position_y", "tip_position_z"), map(float, tip)))
    rot = [device_params.get(f"tool.{k}") for k in ("rx", "ry", "rz")]
    if None not in rot:
        out.update(zip(("tip_orientation_r", "tip_orientation_p", "tip_orientation_y"), _rotvec_rpy(rot)))
    return out


def pal_yaml_text(robot, a, device_params: dict) -> str:
    """`pal_calibration` as YAML (keys in order, full float precision), with a header comment."""
    import yaml

    head = (f"# {robot.name}: calibration by jaxcal in PAL's geometric_calibration layout (joint offsets in rad / m,\n"
            "# camera = device frame in the robot base frame, tip = marker on the tool link). Joint offsets only:\n"
            "# the other identified geometry is in the URDF exports.\n")
    return head + yaml.safe_dump(pal_calibration(robot, a, device_params), sort_keys=False, default_flow_style=False)


def export_writers(robot, kinds) -> dict:
    """kind -> (file name suffix, write(path, a, device_params)) for the `--export` kinds
    ("urdf-rising", "pal-yaml"); the robot must come from a URDF."""
    from jaxcal.io_atomic import write_text_atomic

    table = {"urdf-rising": ("_calibrated_rising.urdf", lambda path, a, dev: write_text_atomic(path, rising_urdf_text(robot, a))),
             "pal-yaml": ("_pal_calibration.yaml", lambda path, a, dev: write_text_atomic(path, pal_yaml_text(robot, a, dev)))}
    unknown = [k for k in kinds if k not in table]
    if unknown:
        raise ValueError(f"--export: unknown kind {unknown[0]!r}; known: {', '.join(table)}")
    for k in kinds:
        _require_urdf(robot, f"--export {k}")
    return {k: table[k] for k in kinds}


__all__ = ["EXPORT_KINDS", "encoder_joints", "export_writers", "pal_calibration", "pal_yaml_text", "read_rising", "rising_urdf_text",
           "rising_values"]
