"""A new URDF for a robot of any joint convention (DH tables, UR kinematics, seed tables).

Each body's local transform is split by its convention as T(q) = A M(q) B (`Convention.motion_split`),
M the motion about or along the joint axis u. In the URDF, body b becomes

    <joint name=b type=revolute|prismatic|fixed> origin = B_parent A_b, axis = u
    <link name=b>                                 (the frame after the motion, before B_b)

(B_parent = I on the base; the robot's constant base pose, if any, is put in front). The tip body and
every leaf get a fixed joint `<b>_frame` with origin B_b to a link `<b>_frame`: the body's own frame,
so `load_urdf(base="base_link", tip=f"{tip}_frame")` has the robot's forward kinematics. A coupled
joint with one source (Cj of seed 001 eq 4) is written as `<mimic joint= multiplier= offset="0">`
(offsets are in the origins); several sources and transmission gains other than 1 cannot be said
in URDF and are errors.
"""

from __future__ import annotations

import numpy as np

from jaxcal.kin.model import Robot
from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.urdf import matrix_rpy

ROOT = "base_link"


def _xml_name(name: str) -> str:
    from xml.sax.saxutils import quoteattr

    return quoteattr(str(name))


def joint_origins(robot: Robot, a=None):
    """Per body: (origin = B_parent A_b as 4x4, B_b as 4x4), at parameters a (default nominal)."""
    a = np.asarray(robot.nominal_np if a is None else a, float)
    ext = np.append(a, 0.0)
    base = np.eye(4)
    if robot.base is not None:
        base[:3, :3], base[:3, 3] = np.asarray(robot.base.R, float), np.asarray(robot.base.p, float)
    out = []
    for b in robot.bodies:
        if b.conv.reads_parent:
            raise RobotFileError(f"robot {robot.name!r}: body {b.name!r} ({b.convention}) has absolute joint angles; "
                                 "URDF joints are relative")
        if b.conv.n_inputs(b.kind) > 1:
            raise RobotFileError(f"robot {robot.name!r}: body {b.name!r} has {b.conv.n_inputs(b.kind)} joint variables; "
                                 "a URDF joint has one")
        row = np.array([ext[i] for i in b.rows], float)
        try:
            A, B = b.conv.motion_split(row, b.kind)
        except NotImplementedError as exc:
            raise RobotFileError(f"robot {robot.name!r}: body {b.name!r}: {exc}") from None
        parent = base if b.parent < 0 else out[b.parent][1]
        out.append((parent @ A, B))
    return out


def body_joint_names(robot: Robot) -> list[str]:
    """URDF joint name per body: the input's name for a body an input drives directly, else the body's name."""
    names = [b.name for b in robot.bodies]
    C = robot.coupling_joint
    for k in range(robot.n_inputs):
        for i, b in enumerate(robot.bodies):
            if not b.inputs:
                continue
            direct = b.inputs[0] == k if C is None else (C[b.inputs[0], k] == 1.0 and np.count_nonzero(C[b.inputs[0]]) == 1)
            if direct:
                names[i] = robot.joint_names[k]
                break
    return names


def _mimic(robot, body, joint_names, direct):
    """(source joint name, multiplier) of a coupled body, or None for a directly driven one."""
    C = robot.coupling_joint
    if C is None or body.name in direct:
        return None
    row = C[body.inputs[0]]
    src = np.flatnonzero(row)
    if len(src) != 1:
        raise RobotFileError(f"robot {robot.name!r}: joint {body.name!r} is coupled to {len(src)} joints; "
                             "URDF <mimic> takes exactly one source joint")
    return joint_names[src[0]], float(row[src[0]])


def _fmt(v) -> str:
    return " ".join(f"{float(x):.17g}" for x in v)


def _origin(T) -> str:
    return f'<origin xyz="{_fmt(T[:3, 3])}" rpy="{_fmt(matrix_rpy(T[:3, :3]))}"/>'


def robot_urdf_text(robot: Robot, a=None) -> str:
    """URDF text of the robot at parameters a (module docstring)."""
    a = np.asarray(robot.nominal_np if a is None else a, float)
    if robot.gains is not None:
        k = a[list(robot.gains)]
        if np.any(np.abs(k - 1.0) > 1e-15):
            raise RobotFileError(f"robot {robot.name!r}: transmission gains {k.tolist()} differ from 1; URDF has no gains")
    if robot.coupling_motor is not None or robot.closure is not None:
        raise RobotFileError(f"robot {robot.name!r}: motor coupling (Cm) and closed loops cannot be written as URDF")
    origins = joint_origins(robot, a)
    names = body_joint_names(robot)
    input_names = list(robot.joint_names)
    direct = {b.name for b, n in zip(robot.bodies, names) if n in input_names}
    link_names = [b.name for b in robot.bodies]
    root = ROOT if ROOT not in link_names else ROOT + "_0"
    has_child = {b.parent for b in robot.bodies}
    lines = ['<?xml version="1.0" encoding="utf-8"?>',
             f"<!-- written by jaxcal from robot {robot.name!r}: one joint per body; the links '<body>_frame' "
             "are the bodies' own frames -->",
             f"<robot name={_xml_name(robot.name)}>", f"  <link name={_xml_name(root)}/>"]
    for i, (b, (T, B)) in enumerate(zip(robot.bodies, origins)):
        parent = root if b.parent < 0 else link_names[b.parent]
        conv = b.conv
        jtype = "fixed" if conv.is_fixed(b.kind) or not b.inputs else ("prismatic" if conv.is_prismatic(b.kind) else "revolute")
        lines.append(f"  <link name={_xml_name(link_names[i])}/>")
        lines.append(f"  <joint name={_xml_name(names[i])} type=\"{jtype}\">")
        lines.append(f"    <parent link={_xml_name(parent)}/>")
        lines.append(f"    <child link={_xml_name(link_names[i])}/>")
        lines.append(f"    {_origin(T)}")
        if jtype != "fixed":
            lines.append(f'    <axis xyz="{_fmt(conv.joint_axis(b.kind))}"/>')
            lo, hi = _limits(robot, b)
            lines.append(f'    <limit lower="{lo:.17g}" upper="{hi:.17g}" effort="0" velocity="0"/>')
            mimic = _mimic(robot, b, input_names, direct)
            if mimic is not None:
                lines.append(f'    <mimic joint={_xml_name(mimic[0])} multiplier="{mimic[1]:.17g}" offset="0"/>')
        lines.append("  </joint>")
        if i == robot.tip % len(robot.bodies) or i not in has_child:
            lines.append(f"  <link name={_xml_name(link_names[i] + '_frame')}/>")
            lines.append(f"  <joint name={_xml_name(names[i] + '_frame')} type=\"fixed\">")
            lines.append(f"    <parent link={_xml_name(link_names[i])}/>")
            lines.append(f"    <child link={_xml_name(link_names[i] + '_frame')}/>")
            lines.append(f"    {_origin(B)}")
            lines.append("  </joint>")
    lines.append("</robot>")
    return "\n".join(lines) + "\n"


def _limits(robot, body):
    """Joint limits of a body: its input's, or for a coupled joint the range of sum_k C_jk q_k over the input box."""
    C = robot.coupling_joint
    j = body.inputs[0]
    if C is None:
        return float(robot.q_min[j]), float(robot.q_max[j])
    row = C[j]
    lo = float(np.sum(np.minimum(row * robot.q_min, row * robot.q_max)))
    hi = float(np.sum(np.maximum(row * robot.q_min, row * robot.q_max)))
    return (lo, hi) if hi > lo else (-np.pi, np.pi)


def urdf_tip_link(robot: Robot) -> str:
    """Link of the written URDF whose frame is the robot's tool frame."""
    return robot.bodies[robot.tip].name + "_frame"
