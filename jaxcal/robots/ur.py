"""Universal Robots kinematics files, as the UR ROS driver and its description package use them.

Two forms are read (recognised by their top-level key) and written:

1. `kinematics:` (the calibration file `ur_calibration` extracts from a controller, and the
   description's default_kinematics.yaml): one entry per joint origin, in chain order,

       kinematics:
         shoulder:  {x: 0, y: 0, z: 0.1625, roll: 0, pitch: 0, yaw: 0}
         upper_arm: {x: 0, y: 0, z: 0, roll: 1.570796327, pitch: 0, yaw: 0}
         forearm:   {...}   wrist_1: {...}   wrist_2: {...}   wrist_3: {...}
         hash: calib_12345

   Each entry is the URDF origin of the joint (shoulder_pan_joint .. wrist_3_joint), metres and
   radians, rpy fixed-axis (R = Rz(yaw) Ry(pitch) Rx(roll)); every joint turns about its own z, and
   tool0 coincides with wrist_3_link (the flange and tool0 rotations of the description cancel). The
   robot is six "urdf" bodies: T_i = Trans(xyz) Rot(rpy) Rz(q_i + offset_i).

2. `dh_parameters:` (the description's physical_parameters.yaml): the standard DH table of the
   arm, keys d1 .. d6, a1 .. a6, alpha1 .. alpha6 (also written d_1, a_1, alpha_1), missing
   entries 0 except alpha, whose default is UR's (pi/2, 0, 0, pi/2, -pi/2, 0); optional theta1 ..
   theta6 are joint offsets. The robot is a `standard_dh` table (`jaxcal.robots.table`).

Writing (`ur_dict(robot, a, form)`): the kinematics form from any serial six-revolute robot whose
joints turn about z after their origin and whose tool frame is the last joint's frame (a UR file
read in either form, or a standard-DH table with a6 = alpha6 = beta6 = 0): origins from
`jaxcal.robots.urdf_write.joint_origins`, joint offsets folded into the rotation; an entry whose
offset is 0 is written with the numbers it was read with. The dh form from a standard-DH robot
with beta = 0. The `hash` read is written back when the parameters are the ones read, else a hash
of the written numbers (`jaxcal_<sha1>`); the driver compares it with the controller's checksum only
to warn.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from jaxcal.kin.joints.urdf import URDF_ROW
from jaxcal.kin.model import Body, Robot
from jaxcal.names import closest
from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.table import row_priority, table_robot
from jaxcal.robots.urdf import matrix_rpy
from jaxcal.robots.urdf_write import joint_origins

UR_SEGMENTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
UR_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")
UR_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
ORIGIN_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
DH_LETTERS = ("d", "a", "alpha", "theta")
UR_LIMIT = 2 * np.pi


def is_ur_kinematics(doc) -> bool:
    """True for a UR kinematics document (`kinematics:` mapping or `dh_parameters:`)."""
    return isinstance(doc, dict) and (isinstance(doc.get("kinematics"), dict) or "dh_parameters" in doc)


def _num(value, where):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RobotFileError(f"{where}: not a number: {value!r}") from None
    if not np.isfinite(v):
        raise RobotFileError(f"{where}: non-finite value {value!r}")
    return v


def robot_from_ur(doc: dict, path: str = "<dict>", name: str = "ur") -> Robot:
    """A robot from a UR kinematics document (module docstring)."""
    if isinstance(doc.get("kinematics"), dict):
        return _from_kinematics(doc["kinematics"], path, name)
    return _from_dh(doc["dh_parameters"], path, name)


def _from_kinematics(kin: dict, path, name) -> Robot:
    extra = [k for k in kin if k not in UR_SEGMENTS and k != "hash"]
    if extra:
        near = closest(str(extra[0]), UR_SEGMENTS, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise RobotFileError(f"{path}, field 'kinematics': unknown entry {extra[0]!r}{hint}; expected {list(UR_SEGMENTS)} and hash")
    names, values, units, priority, bodies = [], [], [], [], []
    for i, (seg, joint) in enumerate(zip(UR_SEGMENTS, UR_JOINTS)):
        entry = kin.get(seg)
        where = f"{path}, field 'kinematics.{seg}'"
        if not isinstance(entry, dict):
            raise RobotFileError(f"{where}: missing, or not a mapping of {list(ORIGIN_KEYS)}")
        bad = [k for k in entry if k not in ORIGIN_KEYS]
        if bad:
            raise RobotFileError(f"{where}: unknown key {bad[0]!r}; expected {list(ORIGIN_KEYS)}")
        row = [_num(entry[k], f"{where}.{k}") if k in entry else 0.0 for k in ORIGIN_KEYS] + [0.0]
        rows = []
        for field, v in zip(URDF_ROW, row):
            rows.append(len(names))
            names.append(f"{joint}.{field}")
            values.append(v)
            units.append("length" if field in ("x", "y", "z") else "angle")
            priority.append(row_priority(field, v, field == "offset", i in (0, 5)))
        bodies.append(Body(joint, "urdf", ("revolute", (0.0, 0.0, 1.0)), i - 1, tuple(rows), (i,)))
    extras = {"source_format": "ur_kinematics", "ur_form": "kinematics", "file_format": "yaml",
              "ur_read": {"values": list(values), "hash": kin.get("hash"),
                          "rows": {seg: dict(kin[seg]) for seg in UR_SEGMENTS}}}
    lim = np.full(6, UR_LIMIT)
    return Robot(name=name, bodies=tuple(bodies), names=tuple(names), nominal_np=np.array(values), units=tuple(units),
                 free_mask=np.ones(len(names), bool), priority=np.array(priority), joint_names=UR_JOINTS,
                 home_np=np.zeros(6), q_min=-lim, q_max=lim, tip=5, extras=extras)


def _dh_key(key: str):
    """(letter, joint 1..6) of a dh_parameters key such as d1, d_1, alpha4; None if it is not one."""
    for letter in ("alpha", "theta", "d", "a"):
        if key.startswith(letter):
            rest = key[len(letter):].lstrip("_")
            if rest.isdigit() and 1 <= int(rest) <= 6:
                return letter, int(rest)
    return None


def _from_dh(dh, path, name) -> Robot:
    if not isinstance(dh, dict):
        raise RobotFileError(f"{path}, field 'dh_parameters': expected a mapping such as {{d1: 0.1625, a2: -0.425, ...}}")
    table = {(letter, i): 0.0 for letter in DH_LETTERS for i in range(1, 7)}
    table.update({("alpha", i): UR_ALPHA[i - 1] for i in range(1, 7)})
    style = "d1"
    for key, value in dh.items():
        parsed = _dh_key(str(key))
        if parsed is None:
            valid = [f"{letter}{i}" for letter in DH_LETTERS for i in range(1, 7)]
            near = closest(str(key), valid, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise RobotFileError(f"{path}, field 'dh_parameters.{key}': unknown key{hint}; expected d1..d6, a1..a6, "
                                 "alpha1..alpha6, theta1..theta6 (or d_1, ...)")
        if "_" in str(key):
            style = "d_1"
        table[parsed] = _num(value, f"{path}, field 'dh_parameters.{key}'")
    rows = [{"name": UR_JOINTS[i - 1], "type": "R", "theta": table[("theta", i)], "d": table[("d", i)],
             "a": table[("a", i)], "alpha": table[("alpha", i)]} for i in range(1, 7)]
    lim = [UR_LIMIT] * 6
    robot = table_robot({"convention": "standard_dh", "joints": rows, "q_min": [-v for v in lim], "q_max": lim},
                        path, None, name)
    robot.extras.update({"source_format": "ur_kinematics", "ur_form": "dh_parameters", "ur_key_style": style})
    return robot


# -- writing ----------------------------------------------------------------------------------------
def ur_dict(robot: Robot, a=None, form: str = "kinematics") -> dict:
    """The UR kinematics document of a robot at parameters a (module docstring); form "kinematics" or "dh_parameters"."""
    if form not in ("kinematics", "dh_parameters"):
        raise ValueError(f"form must be 'kinematics' or 'dh_parameters', got {form!r}")
    a = np.asarray(robot.nominal_np if a is None else a, float)
    _check_serial_six(robot)
    if form == "dh_parameters":
        return {"dh_parameters": _dh_entries(robot, a)}
    read = robot.extras.get("ur_read") if robot.extras.get("ur_form") == "kinematics" else None
    origins = joint_origins(robot, a)
    ext = np.append(a, 0.0)
    tail = origins[-1][1]
    if not np.allclose(tail, np.eye(4), atol=1e-12, rtol=0):
        raise RobotFileError(f"robot {robot.name!r}: the tool frame is not the last joint's frame (a6, alpha6, beta6 "
                             "non-zero); the UR kinematics file has no tool entry")
    kin = {}
    for seg, body, (T, _) in zip(UR_SEGMENTS, robot.bodies, origins):
        if body.convention == "urdf" and read is not None and ext[body.rows[6]] == 0.0:
            row = [float(ext[i]) for i in body.rows[:6]]
            kin[seg] = dict(zip(ORIGIN_KEYS, row))
        else:
            kin[seg] = dict(zip(ORIGIN_KEYS, [float(v) for v in T[:3, 3]] + [float(v) for v in matrix_rpy(T[:3, :3])]))
    same = read is not None and np.array_equal(np.asarray(read["values"]), a)
    kin["hash"] = read["hash"] if same and read["hash"] is not None else _hash(kin)
    return {"kinematics": kin}


def _hash(kin: dict) -> str:
    text = json.dumps({k: kin[k] for k in UR_SEGMENTS}, sort_keys=True)
    return "jaxcal_" + hashlib.sha1(text.encode()).hexdigest()[:16]


def _check_serial_six(robot: Robot) -> None:
    ok = (len(robot.bodies) == 6 and robot.n_inputs == 6 and robot.coupling_joint is None and robot.closure is None
          and all(b.parent == i - 1 and b.inputs == (i,) and b.conv.is_revolute(b.kind) for i, b in enumerate(robot.bodies))
          and all(np.allclose(b.conv.joint_axis(b.kind), (0.0, 0.0, 1.0)) for b in robot.bodies))
    if not ok:
        raise RobotFileError(f"robot {robot.name!r}: a UR kinematics file describes six revolute joints in series, "
                             "each turning about its own z")
    if robot.gains is not None:
        raise RobotFileError(f"robot {robot.name!r}: transmission gains (K) cannot be written in a UR kinematics file")


def _dh_entries(robot: Robot, a) -> dict:
    if any(b.convention != "standard_dh" for b in robot.bodies):
        raise RobotFileError(f"robot {robot.name!r}: the dh_parameters form needs a standard-DH robot; "
                             "write the kinematics form instead")
    ext = np.append(a, 0.0)
    style = robot.extras.get("ur_key_style", "d1")
    out = {}
    rows = [dict(zip(b.conv.row_names, (float(ext[i]) for i in b.rows))) for b in robot.bodies]
    if any(abs(r["beta"]) > 0 for r in rows):
        raise RobotFileError(f"robot {robot.name!r}: non-zero Hayati beta cannot be written in dh_parameters")
    for letter in DH_LETTERS:
        if letter == "theta" and not any(r["theta"] != 0.0 for r in rows):
            continue
        for i, r in enumerate(rows, start=1):
            out[f"{letter}_{i}" if style == "d_1" else f"{letter}{i}"] = r[letter]
    return out
