"""URDF in and out: the chain between two links as a calibratable `Robot`, and back.

Import (`load_urdf(path, base=, tip=)`): the file is parsed by `urdf_parser_py` (the ROS
project's parser); the joints from `base` to `tip` become bodies of the "urdf" convention
(`jaxcal.kin.conventions.urdf_joint`): T = Trans(xyz) Rot(rpy) Motion(axis, q + offset), with
URDF's fixed-axis X-Y-Z rpy (R = Rz(yaw) Ry(pitch) Rx(roll)). Each moving joint carries seven
parameters `<joint>.x .y .z .roll .pitch .yaw .offset`; fixed joints are folded into the origin
of the next moving joint, and fixed joints after the last moving joint become one fixed body
named after the last of them (six parameters, no offset). The table is redundant on purpose
(rpy and offset, the last joint and the marker); `jc.identify` estimates its base set.
Continuous joints are revolute joints without limits. A `<mimic joint= multiplier= offset=>` joint
is coupled (Cj of seed 001 eq 4, `Robot.coupling_joint`): its variable is multiplier x the source's
value, its offset is added to its offset parameter, and the inputs are the chain's independent joints
followed by any mimicked source outside the chain (a mimic of a mimic composes). Inertials of the chain's links are kept in
`robot.extras["inertia"]` (per body: mass, centre of mass and inertia about it, in the body frame).

Export (`save_urdf(robot, path, a)`): the source URDF is rewritten with only the chain's joint
origins changed, so that the file's forward kinematics equals the robot's at `a`. Joint offsets
are folded into the joint origin (revolute: origin rotation times Rot(axis, offset); prismatic:
origin shifted along the axis), so q = 0 in the written file is the calibrated zero; pinocchio,
ROS and MoveIt read plain origins, while `<calibration>` is ignored by their kinematics.
Fixed joints folded at import keep their origins; the moving joint after them absorbs the change.

Checked before use (`check_structure`): UTF-8 text, no DOCTYPE or entity declarations (no entity
expansion, no external files read), a `<robot>` root, unique `<link>` and `<joint>` names, every link
with at most one parent joint, no cycle; each error names the file, the element and its line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import tempfile

import numpy as np

from jaxcal.kin import conventions as cv
from jaxcal.kin.model import Body, Robot
from jaxcal.kin.rotations import principal_rotation
from jaxcal.robots.errors import RobotFileError
from jaxcal.textfile import read_bytes

_TYPE = {"revolute": "revolute", "continuous": "revolute", "prismatic": "prismatic", "fixed": "fixed"}


class URDFError(RobotFileError):
    """A URDF that cannot be turned into a robot; the message names the file and the element."""


# -- homogeneous transforms (numpy, used at the edges only) ---------------------------------------
def rpy_matrix(rpy) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (URDF origin rpy)."""
    r, p, y = (float(v) for v in rpy)
    return principal_rotation(2, y) @ principal_rotation(1, p) @ principal_rotation(0, r)


def matrix_rpy(R) -> np.ndarray:
    """Inverse of `rpy_matrix` with |pitch| <= pi/2; at pitch = +-pi/2 the yaw is set to 0."""
    R = np.asarray(R, float)
    pitch = np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0]))
    if np.hypot(R[0, 0], R[1, 0]) < 1e-12:
        roll = np.arctan2(np.sign(-R[2, 0]) * R[0, 1], R[1, 1])
        return np.array([roll, pitch, 0.0])
    return np.array([np.arctan2(R[2, 1], R[2, 2]), pitch, np.arctan2(R[1, 0], R[0, 0])])


def origin_matrix(xyz, rpy) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rpy_matrix(rpy), np.asarray(xyz, float)
    return T


def _inv(T):
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


# -- parsing --------------------------------------------------------------------------------
@contextlib.contextmanager
def _quiet_parser():
    """urdf_parser_py prints a line per tag it does not model (gazebo, transmission, ...)."""
    import urdf_parser_py.xml_reflection.core as core

    saved = core.on_error
    core.on_error = lambda message: None
    try:
        yield
    finally:
        core.on_error = saved


def _xml_tree(text: str, source: str):
    """The lxml root of a URDF text, parsed without entity expansion, DTD loading or network access."""
    from lxml import etree

    try:
        raw = text.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise URDFError(f"{source}: not valid text ({exc.reason} at character {exc.start})") from None
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False)
    try:
        root = etree.fromstring(raw, parser)
    except etree.XMLSyntaxError as exc:
        raise URDFError(f"{source}: malformed XML: {exc}") from None
    except ValueError as exc:
        raise URDFError(f"{source}: malformed XML: {exc}") from None
    if root is None:
        raise URDFError(f"{source}: malformed XML: no root element")
    info = root.getroottree().docinfo
    if info.doctype or info.internalDTD is not None:
        raise URDFError(f"{source}: a DOCTYPE (entity declarations) is not allowed in a URDF; remove the <!DOCTYPE ...> line")
    if root.tag != "robot":
        raise URDFError(f"{source}, line {root.sourceline}: the root element is <{root.tag}>, expected <robot>")
    return root


def _unique_names(root, tag: str, source: str) -> None:
    """Every <tag> child of <robot> has a name, and no name is given twice (a URDF joint/link name is a key)."""
    first = {}
    for elem in root.findall(tag):
        name = elem.get("name")
        if name is None or not name.strip():
            raise URDFError(f"{source}, line {elem.sourceline}: <{tag}> without a name")
        if name in first:
            raise URDFError(f"{source}, line {elem.sourceline}: duplicate <{tag} name='{name}'> (first on line {first[name]}); "
                            f"{tag} names must be unique")
        first[name] = elem.sourceline


def check_structure(model, source: str) -> None:
    """The joints form a forest of links: each joint's links exist, each link has at most one parent joint,
    and following parents from any link ends at a root (no cycle)."""
    links = {ln.name for ln in model.links}
    parent_joint = {}
    for j in model.joints:
        for role, link in (("parent", j.parent), ("child", j.child)):
            if link not in links:
                raise URDFError(f"{source}: <joint name='{j.name}'>: {role} link {link!r} is not defined by any <link>")
        if j.child in parent_joint:
            raise URDFError(f"{source}: <link name='{j.child}'> has two parents: joints {parent_joint[j.child].name!r} and "
                            f"{j.name!r} both have it as child (a URDF is a tree)")
        parent_joint[j.child] = j
    done = set()
    for start in sorted(links):
        path, link = [], start
        while link in parent_joint and link not in done:
            if link in path:
                cycle = path[path.index(link):] + [link]
                raise URDFError(f"{source}: the joints form a cycle through links {' -> '.join(cycle)} (a URDF is a tree)")
            path.append(link)
            link = parent_joint[link].parent
        done.update(path)


def parse_urdf(text: str, source: str = "<string>"):
    """The urdf_parser_py model of a URDF text; malformed XML, invalid elements, duplicate names, links
    with two parents and cycles raise URDFError (naming the file, the element and the line where known)."""
    from urdf_parser_py.urdf import URDF
    from urdf_parser_py.xml_reflection.core import ParseError

    root = _xml_tree(text, source)
    for tag in ("link", "joint"):
        _unique_names(root, tag, source)
    try:
        with _quiet_parser():
            model = URDF.from_xml_string(text)
    except ParseError as exc:
        raise URDFError(f"{source}: {' '.join(str(exc).split())}") from None
    except (AssertionError, ValueError, TypeError, AttributeError, KeyError, IndexError, SyntaxError) as exc:
        raise URDFError(f"{source}: invalid URDF: {exc}") from None
    check_structure(model, source)
    return model


def _chain(model, base, tip, source):
    """Joints from link `base` to link `tip`, in order."""
    links = {ln.name for ln in model.links}
    for role, link in (("base", base), ("tip", tip)):
        if link not in links:
            raise URDFError(f"{source}: {role} link {link!r}: no <link name='{link}'> in the file")
    parent_joint = {j.child: j for j in model.joints}
    chain, link = [], tip
    while link != base:
        if link not in parent_joint:
            raise URDFError(f"{source}: broken chain: walking up from tip link {tip!r} reached <link name='{link}'>, "
                            f"which has no parent joint, without meeting base link {base!r}")
        joint = parent_joint[link]
        chain.append(joint)
        link = joint.parent
    if not chain:
        raise URDFError(f"{source}: base and tip are the same link {base!r}; no joints between them")
    return chain[::-1]


def _joint_type(joint, source):
    if joint.type not in _TYPE:
        raise URDFError(f"{source}: <joint name='{joint.name}'>: unsupported joint type {joint.type!r}; "
                        f"expected one of {sorted(_TYPE)}")
    return _TYPE[joint.type]


def _axis(joint, source):
    axis = np.array(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], float)
    n = np.linalg.norm(axis)
    if not np.isfinite(n) or n < 1e-12:
        raise URDFError(f"{source}: <joint name='{joint.name}'>/<axis>: axis must be a non-zero vector, got {axis.tolist()}")
    return tuple(float(v) for v in axis / n)


def _origin(joint):
    o = joint.origin
    xyz = [0.0, 0.0, 0.0] if o is None or o.xyz is None else o.xyz
    rpy = [0.0, 0.0, 0.0] if o is None or o.rpy is None else o.rpy
    return origin_matrix(xyz, rpy)


def _finite_origin(joint, source):
    """The joint's origin transform; NaN or inf in xyz/rpy is a URDFError naming the joint."""
    T = _origin(joint)
    if not np.all(np.isfinite(T)):
        raise URDFError(f"{source}: <joint name='{joint.name}'>/<origin>: non-finite value in xyz or rpy")
    return T


def _limits(joint, kind):
    lim = joint.limit
    if joint.type == "continuous" or lim is None or lim.lower is None or lim.upper is None or lim.lower >= lim.upper:
        return (-np.pi, np.pi) if kind == "revolute" else (-1.0, 1.0)
    return float(lim.lower), float(lim.upper)


def _priority(field, value, first_or_last):
    """Seed 001 §4 order: offsets 5, non-zero lengths 4, angles off multiples of pi/2 3, end frames 2."""
    if field == "offset":
        return 5.0
    if field in ("x", "y", "z"):
        if abs(value) > 1e-12:
            return 4.0
    else:
        r = np.mod(value, np.pi / 2)
        if min(r, np.pi / 2 - r) > 1e-9:
            return 3.0
    return 2.0 if first_or_last else 1.0


def _link_inertial(link):
    """(mass, com (3,), inertia about the com in the link frame (3, 3)) of one <link>, or None."""
    ine = link.inertial
    if ine is None or ine.mass is None:
        return None
    T = _origin(ine)
    i = ine.inertia
    I = np.zeros((3, 3)) if i is None else np.array([[i.ixx, i.ixy, i.ixz], [i.ixy, i.iyy, i.iyz], [i.ixz, i.iyz, i.izz]], float)
    return float(ine.mass), T[:3, 3], T[:3, :3] @ I @ T[:3, :3].T


def _merge_inertia(parts):
    """Mass, centre of mass and inertia about it of rigidly joined parts [(name, T_body_link, mass, com, I)]."""
    mass = sum(m for _, _, m, _, _ in parts)
    if mass <= 0:
        return {"links": tuple(p[0] for p in parts), "mass": 0.0, "com": np.zeros(3), "inertia": np.zeros((3, 3))}
    coms = [T[:3, :3] @ c + T[:3, 3] for _, T, _, c, _ in parts]
    com = sum(m * c for (_, _, m, _, _), c in zip(parts, coms)) / mass
    inertia = np.zeros((3, 3))
    for (_, T, m, _, I), c in zip(parts, coms):
        d = c - com
        inertia += T[:3, :3] @ I @ T[:3, :3].T + m * (d @ d * np.eye(3) - np.outer(d, d))
    return {"links": tuple(p[0] for p in parts), "mass": mass, "com": com, "inertia": inertia}


def _default_link(model, role: str, source: str) -> str:
    """The only root (role "base") or leaf (role "tip") link of the file; an error naming a few when there are several."""
    children, parents = {j.child for j in model.joints}, {j.parent for j in model.joints}
    found = sorted(ln.name for ln in model.links if ln.name not in (children if role == "base" else parents))
    if len(found) != 1:
        what = "first link of the chain" if role == "base" else "tool link"
        raise URDFError(f"{source}: give {role}= (the {what}); the file has {len(found)} {'root' if role == 'base' else 'leaf'} "
                        f"links, e.g. {found[:5]}")
    return found[0]


def tree_groups(chains, tip_links) -> list[tuple[list, object, int]]:
    """The bodies of the union of `chains` (joint lists from the base): (fixed joints folded before, the joint
    that carries the origin, index of the parent body or -1), each joint of the union once, parents first.

    Along a chain fixed joints fold into the next moving joint; a fixed joint whose child is a tip link ends
    a body of its own (as the fixed joints after a chain's last moving joint do), so that a link read as a
    tip, or passed on the way to another tip, is one body of the tree and its parameters are shared."""
    groups, body_of = [], {}
    for chain in chains:
        pending, parent = [], -1
        for joint in chain:
            if _TYPE.get(joint.type) == "fixed" and joint.child not in tip_links:
                pending.append(joint)
                continue
            if joint.name not in body_of:
                body_of[joint.name] = len(groups)
                groups.append((pending, joint, parent))
            pending, parent = [], body_of[joint.name]
    return groups


def robot_from_urdf(text: str, base: str | None = None, tip: str | None = None, source: str = "<string>",
                    name: str | None = None, tips=None) -> Robot:
    """Robot of the chain from link `base` (default: the root link) to link `tip` (default: the
    only leaf link) of a URDF text; or, with `tips=` (link names, a link once per marker read on it),
    the tree of the chains from `base` to each of them, shared links once (`Robot.tips`: marker slot
    k rides on body tips[k])."""
    model = parse_urdf(text, source)
    if tips is not None and tip is not None:
        raise URDFError(f"{source}: give tip= (one chain) or tips= (a tree), not both")
    base = base if base is not None else _default_link(model, "base", source)
    tip_links = [str(t) for t in tips] if tips is not None else [tip if tip is not None else _default_link(model, "tip", source)]
    if not tip_links:
        raise URDFError(f"{source}: tips= names no link")
    distinct = list(dict.fromkeys(tip_links))
    chains = [_chain(model, base, t, source) for t in distinct]
    for joint in (j for chain in chains for j in chain):
        _joint_type(joint, source)  # an unsupported joint type is named before anything else is read
    link_by_name = {ln.name: ln for ln in model.links}
    groups = tree_groups(chains, set(distinct))
    ends = {chain[-1].name for chain in chains}

    names, values, units, priority, bodies, moving = [], [], [], [], [], []
    body_meta, inertia = [], []
    for b, (folded, joint, parent) in enumerate(groups):
        kind = _joint_type(joint, source)
        F = np.eye(4)
        for f in folded:
            F = F @ _finite_origin(f, source)
        T = F @ _finite_origin(joint, source)
        geometry = list(T[:3, 3]) + list(matrix_rpy(T[:3, :3]))
        fields = cv.URDF_ROW if kind != "fixed" else cv.URDF_ROW[:6]
        rows = []
        for field, value in zip(fields, geometry + [0.0]):
            rows.append(len(names))
            names.append(f"{joint.name}.{field}")
            values.append(float(value))
            units.append("length" if field in ("x", "y", "z") or (field == "offset" and kind == "prismatic") else "angle")
            priority.append(_priority(field, value, parent < 0 or joint.name in ends))
        if kind == "fixed":
            rows.append(-1)
        inputs = ()
        if kind != "fixed":
            inputs = (len(moving),)
            moving.append((joint, rows[6]))
        axis = _axis(joint, source) if kind != "fixed" else (0.0, 0.0, 1.0)
        bodies.append(Body(joint.name, "urdf", (kind, axis), parent, tuple(rows), inputs))
        body_meta.append({"joint": joint.name, "folded": tuple(f.name for f in folded), "type": joint.type})
        chain = next(c for c in chains if joint in c)
        inertia.append(_body_inertia(chain, joint, link_by_name, kind))

    joint_names, lo, hi, C = _mimic_coupling(model, moving, values, source)
    home = np.clip(np.zeros(len(lo)), lo, hi)
    body_index = {g[1].name: b for b, g in enumerate(groups)}
    tip_bodies = [body_index[_chain(model, base, t, source)[-1].name] for t in tip_links]
    extras = {"urdf_text": text, "urdf_source": source, "base_link": base, "tip_link": tip_links[0],
              "urdf_bodies": tuple(body_meta), "inertia": tuple(inertia)}
    if tips is not None:
        extras["tip_links"] = tuple(tip_links)
    return Robot(
        name=name or model.name or "urdf", bodies=tuple(bodies), names=tuple(names), nominal_np=np.array(values),
        units=tuple(units), free_mask=np.ones(len(names), bool), priority=np.array(priority),
        joint_names=tuple(joint_names), home_np=home, q_min=lo, q_max=hi, tip=tip_bodies[0], coupling_joint=C,
        extras=extras, tips=tuple(tip_bodies) if tips is not None and len(tip_links) > 1 else (),
    )


def mimic_source(model, name: str, source: str):
    """(independent joint, multiplier, offset) of a joint: q_name = multiplier q_source + offset, following
    <mimic> links (a mimic of a mimic composes); a missing source or a mimic cycle is a URDFError."""
    by_name = {j.name: j for j in model.joints}
    mult, off, seen = 1.0, 0.0, [name]
    joint = by_name[name]
    while joint.mimic is not None:
        src = joint.mimic.joint
        if src not in by_name:
            raise URDFError(f"{source}: <joint name='{joint.name}'>/<mimic joint='{src}'>: no joint named {src!r}")
        if src in seen:
            raise URDFError(f"{source}: <mimic> joints form a cycle {' -> '.join(seen + [src])}")
        m = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
        o = 0.0 if joint.mimic.offset is None else float(joint.mimic.offset)
        if not (np.isfinite(m) and np.isfinite(o)):
            raise URDFError(f"{source}: <joint name='{joint.name}'>/<mimic>: non-finite multiplier or offset")
        mult, off = mult * m, off * m + o
        seen.append(src)
        joint = by_name[src]
    return joint, mult, off


def _mimic_coupling(model, moving, values, source):
    """Inputs, limits and Cj (seed 001 eq 4) of the chain's moving joints [(joint, offset parameter index)].

    The independent joints of the chain are the inputs, in chain order, followed by the sources of
    <mimic> joints that lie outside the chain; a mimic joint's variable is multiplier x its source and
    its offset is added to the joint's offset parameter (`values`, changed in place). Cj is None when
    no joint of the chain mimics another."""
    resolved = [mimic_source(model, j.name, source) for j, _ in moving]
    inputs = [j for j, _ in moving if j.mimic is None]
    for src, _, _ in resolved:
        if all(src.name != j.name for j in inputs):
            inputs.append(src)
    lo, hi = [], []
    for j in inputs:
        lo_j, hi_j = _limits(j, _joint_type(j, source))
        if not (np.isfinite(lo_j) and np.isfinite(hi_j)):
            raise URDFError(f"{source}: <joint name='{j.name}'>/<limit>: non-finite lower/upper ({lo_j}, {hi_j})")
        lo.append(lo_j)
        hi.append(hi_j)
    names = [j.name for j in inputs]
    C = None
    if any(j.mimic is not None for j, _ in moving) or len(inputs) != len(moving):
        C = np.zeros((len(moving), len(inputs)))
        for m, ((joint, offset_index), (src, mult, off)) in enumerate(zip(moving, resolved)):
            C[m, names.index(src.name)] = mult
            values[offset_index] += off
    return tuple(names), np.array(lo), np.array(hi), C


def _body_inertia(chain, joint, link_by_name, kind):
    """Inertia of the links moving rigidly with a moving joint's child link, in that link's frame.
    The fixed body that ends a chain carries none (its links move with the last moving body)."""
    if kind == "fixed":
        return _merge_inertia([])
    start = chain.index(joint)
    parts, T = [], np.eye(4)
    for k in range(start, len(chain)):
        if k > start:
            if _TYPE[chain[k].type] != "fixed":
                break
            T = T @ _origin(chain[k])
        data = _link_inertial(link_by_name[chain[k].child])
        if data is not None:
            parts.append((chain[k].child, T.copy()) + data)
    return _merge_inertia(parts)


def load_urdf(path: str, base: str | None = None, tip: str | None = None, name: str | None = None, tips=None) -> Robot:
    """Robot of the chain from link `base` to link `tip`, or of the tree to the links `tips`, of a URDF file
    (see module docstring and `robot_from_urdf`)."""
    path = str(path)
    raw = read_bytes(path, URDFError)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise URDFError(f"{path}, line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x})") from None
    robot = robot_from_urdf(text, base, tip, source=path, name=name, tips=tips)
    robot.extras["urdf_path"] = os.path.realpath(path)
    return robot


# -- joint compliance under gravity ---------------------------------------------------------
GRAVITY = (0.0, 0.0, -9.81)


def gravity_torques(robot: Robot, q, a=None, gravity=GRAVITY) -> np.ndarray:
    """Gravity torque (N m) on each revolute joint of a URDF chain, (N, n_revolute), from the
    link masses and centres of mass in `robot.extras["inertia"]` and the frames at parameters a:
    tau_j = u_j . sum_{i >= j} (c_i - o_j) x (m_i g), with u_j the joint axis and o_j its origin.
    Only the chain's links count (branches hanging off it are not included)."""
    from jaxcal.kin.model import frames

    a = robot.nominal if a is None else a
    f = frames(robot, a, np.atleast_2d(np.asarray(q, float)))
    R, p = np.asarray(f.R), np.asarray(f.p)
    mass = np.array([b["mass"] for b in robot.extras["inertia"]])
    com = np.stack([np.asarray(b["com"], float) for b in robot.extras["inertia"]])
    centres = p + np.einsum("nbij,bj->nbi", R, com)
    force = mass[:, None] * np.asarray(gravity, float)[None, :]
    out = []
    for j, body in enumerate(robot.bodies):
        if body.kind[0] != "revolute":
            continue
        moment = np.cross(centres[:, j:] - p[:, j:j + 1], force[None, j:]).sum(axis=1)
        out.append(np.einsum("ni,ni->n", R[:, j] @ np.asarray(body.kind[1]), moment))
    return np.stack(out, axis=1)


def with_gravity_compliance(robot: Robot) -> Robot:
    """The robot with a compliance k_j (rad/(N m), parameter `<joint>.compliance`) on every revolute
    joint: angle = q + offset + k_j tau_j, where tau_j, the gravity torque from `gravity_torques` at
    the nominal geometry, is an extra joint input named `<joint>.tau` (after the joint values)."""
    if robot.coupling_joint is not None:
        raise ValueError(f"robot {robot.name!r}: gravity compliance is not available for coupled (<mimic>) joints")
    names, values, units, priority = list(robot.names), list(robot.nominal_np), list(robot.units), list(robot.priority)
    n, bodies, taus = robot.n_inputs, [], []
    for body in robot.bodies:
        if body.kind[0] != "revolute":
            bodies.append(body)
            continue
        names.append(f"{body.name}.compliance")
        values.append(0.0)
        units.append("angle")  # rad per N m; typical values 1e-5..1e-3, sized like a small angle
        priority.append(4.0)
        bodies.append(dataclasses.replace(body, rows=body.rows + (len(names) - 1,), inputs=body.inputs + (n + len(taus),)))
        taus.append(f"{body.name}.tau")
    k = len(taus)
    return robot.replace(
        name=f"{robot.name}+compliance", bodies=tuple(bodies), names=tuple(names), nominal_np=np.array(values),
        units=tuple(units), free_mask=np.ones(len(names), bool), priority=np.array(priority),
        joint_names=robot.joint_names + tuple(taus), home_np=np.concatenate([robot.home_np, np.zeros(k)]),
        q_min=np.concatenate([robot.q_min, np.full(k, -1e3)]), q_max=np.concatenate([robot.q_max, np.full(k, 1e3)]),
        extras={**robot.extras, "compliance_of": robot},
    )


def compliance_inputs(robot: Robot, q) -> np.ndarray:
    """Joint inputs of `with_gravity_compliance(robot)`: q followed by the nominal gravity torques."""
    q = np.atleast_2d(np.asarray(q, float))
    return np.concatenate([q, gravity_torques(robot, q)], axis=1)


# -- export ---------------------------------------------------------------------------------
def _calibrated_origin(robot: Robot, body: Body, a_ext) -> np.ndarray:
    """The body's origin at parameters a with the joint offset folded in (module docstring)."""
    row = np.array([a_ext[i] for i in body.rows], float)
    T = origin_matrix(row[0:3], row[3:6])
    joint_type, axis = body.kind
    if joint_type == "revolute":
        T[:3, :3] = T[:3, :3] @ np.asarray(cv.axis_rotation(axis, row[6]))
    elif joint_type == "prismatic":
        T[:3, 3] = T[:3, 3] + T[:3, :3] @ (np.asarray(axis) * row[6])
    return T


def urdf_text(robot: Robot, a=None) -> str:
    """The source URDF with the chain's joint origins set to the robot's geometry at `a`."""
    from lxml import etree

    if "urdf_text" not in robot.extras:
        raise URDFError(f"robot {robot.name!r} was not loaded from a URDF; only URDF-loaded robots can be exported")
    a = np.asarray(robot.nominal_np if a is None else a, float)
    if a.shape != (robot.n_params,):
        raise ValueError(f"parameters must have shape ({robot.n_params},), got {a.shape}")
    a_ext = np.append(a, 0.0)
    root = etree.fromstring(robot.extras["urdf_text"].encode())
    joints = {j.get("name"): j for j in root.findall("joint")}

    def origin_of(name):
        o = joints[name].find("origin")
        get = (lambda key: [float(v) for v in (o.get(key) or "0 0 0").split()]) if o is not None else (lambda key: [0.0] * 3)
        return origin_matrix(get("xyz"), get("rpy"))

    for body, meta in zip(robot.bodies, robot.extras["urdf_bodies"]):
        F = np.eye(4)
        for f in meta["folded"]:
            F = F @ origin_of(f)
        T = _inv(F) @ _calibrated_origin(robot, body, a_ext)
        elem = joints[meta["joint"]]
        origin = elem.find("origin")
        if origin is None:
            origin = etree.SubElement(elem, "origin")
        origin.set("xyz", " ".join(f"{v:.17g}" for v in T[:3, 3]))
        origin.set("rpy", " ".join(f"{v:.17g}" for v in matrix_rpy(T[:3, :3])))
        mimic = elem.find("mimic")
        if mimic is not None:  # its offset was added to the joint's offset parameter, now in the origin
            mimic.set("offset", "0")
    note = etree.Comment(f" calibrated by jaxcal: origins of the joints {', '.join(m['joint'] for m in robot.extras['urdf_bodies'])} "
                         "carry the identified geometry; joint offsets are folded into them ")
    root.insert(0, note)
    return etree.tostring(root, xml_declaration=True, encoding="utf-8").decode()


def save_urdf(robot: Robot, path: str, a=None) -> str:
    """Write the calibrated URDF atomically (temp file in the same folder, then rename); never over
    the URDF the robot was loaded from."""
    path = str(path)
    src = robot.extras.get("urdf_path")
    if src is not None and os.path.realpath(path) == src:
        raise URDFError(f"{path}: refusing to overwrite the input URDF; choose another output path")
    text = urdf_text(robot, a)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".urdf.tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


__all__ = ["GRAVITY", "URDFError", "check_structure", "compliance_inputs", "gravity_torques", "load_urdf", "with_gravity_compliance",
           "matrix_rpy", "parse_urdf", "robot_from_urdf", "rpy_matrix", "save_urdf", "urdf_text"]
