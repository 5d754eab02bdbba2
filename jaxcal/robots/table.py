"""DH tables with a named convention, a parent column, fixed 6-D transform rows and joint coupling.

    name: kr6                               # optional, default the file name
    convention: standard_dh                 # standard_dh | craig_mdh | khalil_kleinfinger
    units: {length: mm, angle: deg}         # default m, rad
    columns: [name, parent, type, theta, d, a, alpha]
    joints:
      - [A1, base, R, 0, 400, 25, -90]
      - [A2, A1, R, 0, 0, 455, 0]
      - {name: flange, parent: A2, type: transform, xyz: [0, 0, 80], rpy: [0, 0, 180]}
    coupling:                               # optional: joint value = sum_k C_jk q_k + offset
      A3: {A1: -1, A2: -1, offset: 0}
    tip: flange                             # optional, default the last row
    home / q_min / q_max / joint_names      # optional, one entry per independent joint (file units)

Geometry columns per convention (each row of the convention's transform; `beta` optional, default 0):

| convention | columns | transform of one row |
|---|---|---|
| standard_dh | theta d a alpha [beta] | Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta) |
| craig_mdh | alpha a theta d [beta] | Ry(beta) Rx(alpha) Tx(a) Rz(theta) Tz(d) |
| khalil_kleinfinger | alpha d theta r [beta] | Ry(beta) Rx(alpha) Tx(d) Rz(theta) Tz(r) |

Other columns: `name` (default j1, j2, ...), `parent` (a row name or `base`; default the row
above), `type` (R revolute: the variable adds to theta; P prismatic: adds to d (r in KK); F a
constant DH row; default R), `K` (transmission gain of the row's joint, seed 001 eq 4; gives gain
parameters `<name>.K`). A row is a list in `columns` order or a mapping by column name; a
`type: transform` row is a mapping with `xyz` and `rpy` (URDF's fixed-axis roll-pitch-yaw,
R = Rz(yaw) Ry(pitch) Rx(roll)): a general constant 6-D frame (base, tool flange, a branch point).

Coupling reuses Cj of seed 001 eq 4 (`Robot.coupling_joint`): the robot's inputs are the independent
moving rows; qj = C q gives every moving row's variable, the coupled rows' entries of C from the
`coupling` mapping (source joints must be independent), and a coupling offset is added to the row's
joint-offset entry (theta or d). Data then carry only the independent joint columns.

Errors name the file, the row and its line (when read from a file) and the field.
"""

from __future__ import annotations

import numpy as np

from jaxcal.kin.joints.dh import CRAIG_ROW, DH_ROW
from jaxcal.kin.joints.mdh import MDH_ROW
from jaxcal.kin.model import Body, Robot
from jaxcal.names import closest, duplicates
from jaxcal.robots.errors import RobotFileError

# table convention -> (registered kin convention, its geometry letters)
TABLE_CONVENTIONS = {
    "standard_dh": ("standard_dh", DH_ROW),
    "craig_mdh": ("craig_mdh", CRAIG_ROW),
    "khalil_kleinfinger": ("mdh", MDH_ROW),
}
TABLE_OF_CONVENTION = {kin: table for table, (kin, _) in TABLE_CONVENTIONS.items()}
META_COLUMNS = ("name", "parent", "type", "K")
TYPE_SIGMA = {"R": 0, "revolute": 0, "P": 1, "prismatic": 1, "F": 2, "fixed": 2}
TRANSFORM_TYPES = ("T", "transform")
XYZRPY = ("x", "y", "z", "roll", "pitch", "yaw")
LENGTHS = {"d", "a", "r", "x", "y", "z"}
BASE = "base"


def _where(path, lines, i):
    """'path, row i (line L)' for error messages; rows count from 1."""
    line = f" (line {lines[i - 1]})" if lines and i - 1 < len(lines) else ""
    return f"{path}, row {i}{line}"


def _num(value, where, field):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RobotFileError(f"{where}, field '{field}': not a number: {value!r}") from None
    if not np.isfinite(v):
        raise RobotFileError(f"{where}, field '{field}': non-finite value {value!r}")
    return v


def _multiple_of_half_pi(x: float) -> bool:
    r = np.mod(x, np.pi / 2)
    return min(r, np.pi / 2 - r) < 1e-9


def row_priority(field: str, value: float, is_offset: bool, at_end: bool) -> float:
    """Seed 001 §4: 5 joint offsets, 4 non-zero lengths, 3 angles off multiples of pi/2 (beta excepted),
    2 parameters of the first/last frames, 1 the rest."""
    if is_offset:
        return 5.0
    if field in LENGTHS and abs(value) > 1e-12:
        return 4.0
    if field not in LENGTHS and field != "beta" and not _multiple_of_half_pi(value):
        return 3.0
    return 2.0 if at_end else 1.0


def _columns(doc, path, letters):
    cols = doc.get("columns")
    if cols is None:
        return None
    if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
        raise RobotFileError(f"{path}: field 'columns' must be a list of column names")
    dup = duplicates(cols)
    if dup:
        raise RobotFileError(f"{path}: field 'columns': column {dup[0]!r} given twice")
    known = tuple(letters) + META_COLUMNS
    for c in cols:
        if c not in known:
            near = closest(c, known, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise RobotFileError(f"{path}: field 'columns': unknown column {c!r}{hint}; this convention has {list(known)}")
    missing = [c for c in letters if c != "beta" and c not in cols]
    if missing:
        raise RobotFileError(f"{path}: field 'columns': missing column(s) {missing} of convention {doc.get('convention')!r}")
    return cols


def parse_rows(doc, path, lines, letters):
    """The rows as dicts {name, parent, type, geometry..., K} in file order (values converted to SI)."""
    rows = doc.get("joints")
    if not isinstance(rows, list) or not rows:
        raise RobotFileError(f"{path}: 'joints' must be a non-empty list of rows")
    cols = _columns(doc, path, letters)
    ang, lng = _scales(doc, path)
    out = []
    for i, raw in enumerate(rows, start=1):
        where = _where(path, lines, i)
        if isinstance(raw, dict):
            entry = dict(raw)
        elif isinstance(raw, (list, tuple)):
            if cols is None:
                raise RobotFileError(f"{where}: a list row needs a 'columns' header (or write the row as a mapping)")
            if len(raw) != len(cols):
                raise RobotFileError(f"{where}: expected {len(cols)} fields {cols}, got {len(raw)}")
            entry = dict(zip(cols, raw))
        else:
            raise RobotFileError(f"{where}: a row must be a list or a mapping, got {raw!r}")
        out.append(_parse_row(entry, i, where, letters, ang, lng))
    return out


def _scales(doc, path):
    units = doc.get("units") or {}
    if not isinstance(units, dict):
        raise RobotFileError(f"{path}: field 'units' must be a mapping such as {{length: mm, angle: deg}}")
    angle, length = units.get("angle", "rad"), units.get("length", "m")
    if angle not in ("rad", "deg"):
        raise RobotFileError(f"{path}: units.angle must be 'rad' or 'deg', got {angle!r}")
    if length not in ("m", "mm"):
        raise RobotFileError(f"{path}: units.length must be 'm' or 'mm', got {length!r}")
    return (np.pi / 180.0 if angle == "deg" else 1.0), (1e-3 if length == "mm" else 1.0)


def _parse_row(entry, i, where, letters, ang, lng):
    name = entry.get("name", f"j{i}")
    if not isinstance(name, str) or not name.strip() or name == BASE:
        raise RobotFileError(f"{where}, field 'name': must be a non-empty name other than {BASE!r}, got {name!r}")
    parent = entry.get("parent")
    if parent is not None and not isinstance(parent, str):
        raise RobotFileError(f"{where}, field 'parent': must be a row name or {BASE!r}, got {parent!r}")
    typ = str(entry.get("type", "R"))
    if typ in TRANSFORM_TYPES:
        extra = sorted(set(entry) - {"name", "parent", "type", "xyz", "rpy"})
        if extra:
            raise RobotFileError(f"{where}: a transform row takes name, parent, type, xyz, rpy; unknown field(s) {extra}")
        values = []
        for key, scale in (("xyz", lng), ("rpy", ang)):
            v = entry.get(key, [0.0, 0.0, 0.0])
            if not isinstance(v, (list, tuple)) or len(v) != 3:
                raise RobotFileError(f"{where}, field '{key}': expected 3 numbers, got {v!r}")
            values += [_num(x, where, key) * scale for x in v]
        return {"name": name, "parent": parent, "type": "transform", "values": dict(zip(XYZRPY, values)), "line": where}
    if typ not in TYPE_SIGMA:
        raise RobotFileError(f"{where}, field 'type': unknown joint type {typ!r}; expected R, P, F or transform")
    known = set(letters) | set(META_COLUMNS)
    for key in entry:
        if key not in known:
            near = closest(str(key), sorted(known), n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise RobotFileError(f"{where}: unknown field {key!r}{hint}")
    values = {}
    for f in letters:
        if f not in entry and f != "beta":
            raise RobotFileError(f"{where}: missing field '{f}'")
        v = _num(entry.get(f, 0.0), where, f)
        values[f] = v * (lng if f in LENGTHS else ang)
    gain = _num(entry["K"], where, "K") if "K" in entry and entry["K"] is not None else None
    return {"name": name, "parent": parent, "type": TYPE_SIGMA[typ], "values": values, "K": gain, "line": where}


def order_rows(rows, path):
    """Parent index per row and a parents-first order; duplicate names, unknown parents and cycles are errors."""
    index = {}
    for k, row in enumerate(rows):
        if row["name"] in index:
            raise RobotFileError(f"{row['line']}, field 'name': joint {row['name']!r} given twice "
                                 f"(first in {rows[index[row['name']]]['line']}); names in the parent column must be unique")
        index[row["name"]] = k
    parent = []
    for k, row in enumerate(rows):
        p = row["parent"]
        if p is None:
            parent.append(k - 1)
        elif p == BASE:
            parent.append(-1)
        elif p in index:
            parent.append(index[p])
        else:
            near = closest(p, list(index) + [BASE], n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise RobotFileError(f"{row['line']}, field 'parent': no row named {p!r}{hint}")
    order, state = [], [0] * len(rows)  # 0 new, 1 on the current path, 2 placed
    for start in range(len(rows)):
        path_ = []
        k = start
        while k >= 0 and state[k] == 0:
            state[k] = 1
            path_.append(k)
            k = parent[k]
        if k >= 0 and state[k] == 1:
            cycle = [rows[j]["name"] for j in path_[path_.index(k):]] + [rows[k]["name"]]
            raise RobotFileError(f"{path}, field 'parent': the parents form a cycle {' -> '.join(cycle)} "
                                 f"({rows[k]['line']}); the rows must form a tree rooted at {BASE!r}")
        for j in reversed(path_):
            state[j] = 2
            order.append(j)
    return parent, order


def parse_coupling(doc, path, moving, independent):
    """{coupled row: ({source row: coefficient}, offset)} from the `coupling` mapping."""
    spec = doc.get("coupling") or {}
    if not isinstance(spec, dict):
        raise RobotFileError(f"{path}: field 'coupling' must map a joint to {{source: coefficient, ..., offset: value}}")
    out = {}
    for joint, terms in spec.items():
        where = f"{path}, field 'coupling', joint {joint!r}"
        if joint not in moving:
            raise RobotFileError(f"{where}: not a moving row of the table (moving rows: {sorted(moving)})")
        if not isinstance(terms, dict) or not terms:
            raise RobotFileError(f"{where}: expected a mapping {{source joint: coefficient, ..., offset: value}}")
        coef, offset = {}, 0.0
        for src, c in terms.items():
            if src == "offset":
                offset = _num(c, where, "offset")
                continue
            if src not in independent:
                why = "is itself coupled" if src in moving else "is not a moving row"
                raise RobotFileError(f"{where}: source {src!r} {why}; sources must be independent joints")
            coef[src] = _num(c, where, src)
        out[joint] = (coef, offset)
    return out


def table_robot(doc, path="<dict>", lines=None, name="robot") -> Robot:
    """Build a robot from a parsed DH-table document (module docstring)."""
    table_conv = doc["convention"]
    kin_conv, letters = TABLE_CONVENTIONS[table_conv]
    rows = parse_rows(doc, path, lines, letters)
    parent, order = order_rows(rows, path)
    pos = {k: n for n, k in enumerate(order)}  # file row -> body index
    children = {parent[k] for k in range(len(rows))}
    moving = [rows[k]["name"] for k in order if rows[k]["type"] in (0, 1)]
    coupling = parse_coupling(doc, path, set(moving), set(moving) - set((doc.get("coupling") or {})))
    independent = [n for n in moving if n not in coupling]
    if not independent:
        raise RobotFileError(f"{path}: the table has no independent moving joint")
    names, values, units, priority = [], [], [], []
    bodies, gains = [], []
    by_name = {rows[k]["name"]: k for k in order}
    for k in order:
        row = rows[k]
        at_end = parent[k] < 0 or k not in children
        idx = []
        if row["type"] == "transform":
            for f in XYZRPY:
                v = row["values"][f]
                idx.append(len(names))
                names.append(f"{row['name']}.{f}")
                values.append(v)
                units.append("length" if f in LENGTHS else "angle")
                priority.append(row_priority(f, v, False, at_end))
            idx.append(-1)  # the URDF row's joint offset: none for a constant frame
            conv, kind, inputs = "urdf", ("fixed", (0.0, 0.0, 1.0)), ()
        else:
            sigma = row["type"]
            offset_field = {0: letters.index("theta"), 1: letters.index("d" if kin_conv != "mdh" else "r")}.get(sigma)
            for j, f in enumerate(letters):
                v = row["values"][f]
                if j == offset_field and row["name"] in coupling:
                    v += coupling[row["name"]][1]
                idx.append(len(names))
                names.append(f"{row['name']}.{f}")
                values.append(v)
                units.append("length" if f in LENGTHS else "angle")
                priority.append(row_priority(f, v, j == offset_field, at_end))
            conv, kind = kin_conv, sigma
            inputs = (moving.index(row["name"]),) if sigma in (0, 1) else ()
            if row["K"] is not None and sigma in (0, 1) and row["name"] in coupling and row["K"] != 1.0:
                raise RobotFileError(f"{row['line']}, field 'K': a coupled joint has no gain of its own "
                                     f"(its coefficients are in 'coupling'); give 1 or leave it empty")
        bodies.append(Body(row["name"], conv, kind, pos[parent[k]] if parent[k] >= 0 else -1, tuple(idx), inputs))
    has_gains = any(r.get("K") is not None for r in rows)
    if has_gains:
        for n in independent:
            g = rows[by_name[n]].get("K")
            names.append(f"{n}.K")
            values.append(1.0 if g is None else g)
            units.append("gain")
            priority.append(5.0)
            gains.append(len(names) - 1)
    C = None
    if coupling:
        C = np.zeros((len(moving), len(independent)))
        for m, n in enumerate(moving):
            if n in coupling:
                for src, c in coupling[n][0].items():
                    C[m, independent.index(src)] = c
            else:
                C[m, independent.index(n)] = 1.0
    tip = doc.get("tip")
    if tip is None:
        tip_body = pos[len(rows) - 1]
    elif tip in by_name:
        tip_body = pos[by_name[tip]]
    else:
        raise RobotFileError(f"{path}, field 'tip': no row named {tip!r}")
    n_in = len(independent)
    ang, lng = _scales(doc, path)
    prismatic = [rows[by_name[n]]["type"] == 1 for n in independent]
    lo = np.array([-1.0 if p else -np.pi for p in prismatic])
    hi = np.array([1.0 if p else np.pi for p in prismatic])
    joint_names = doc.get("joint_names", independent)
    common = {}
    for key, default in (("home", np.clip(np.zeros(n_in), lo, hi)), ("q_min", lo), ("q_max", hi)):
        v = doc.get(key)
        if v is None:
            common[key] = default
            continue
        if not isinstance(v, list) or len(v) != n_in:
            raise RobotFileError(f"{path}, field '{key}': expected {n_in} numbers (one per independent joint {independent})")
        common[key] = np.array([_num(x, path, key) for x in v]) * np.where(prismatic, lng, ang)
    if len(joint_names) != n_in:
        raise RobotFileError(f"{path}, field 'joint_names': expected {n_in} names (one per independent joint {independent})")
    offsets = {n: off for n, (_, off) in coupling.items()}
    return Robot(
        name=name, bodies=tuple(bodies), names=tuple(names), nominal_np=np.array(values, float),
        units=tuple(units), free_mask=np.ones(len(names), bool), priority=np.array(priority),
        joint_names=tuple(joint_names), home_np=common["home"], q_min=common["q_min"], q_max=common["q_max"],
        tip=tip_body, gains=tuple(gains) if has_gains else None,
        coupling_joint=C,
        extras={"table": {"convention": table_conv, "coupling_offsets": offsets}, "file_format": "yaml"},
    )


# -- writing ----------------------------------------------------------------------------------------
def table_convention_of(robot: Robot) -> str:
    """The table convention of a robot whose bodies are DH rows of one convention and/or transform rows."""
    kins = {b.convention for b in robot.bodies if not (b.convention == "urdf" and b.kind[0] == "fixed")}
    if len(kins) != 1 or next(iter(kins)) not in TABLE_OF_CONVENTION:
        raise RobotFileError(f"robot {robot.name!r}: bodies of convention(s) {sorted(kins)} cannot be written as one DH table "
                             f"({sorted(TABLE_CONVENTIONS)} with transform rows)")
    return TABLE_OF_CONVENTION[next(iter(kins))]


def table_dict(robot: Robot, a=None) -> dict:
    """The DH-table document of a robot (parameters a, default nominal), in metres and radians."""
    a = np.asarray(robot.nominal_np if a is None else a, float)
    ext = np.append(a, 0.0)
    table_conv = table_convention_of(robot)
    _, letters = TABLE_CONVENTIONS[table_conv]
    offsets = (robot.extras.get("table") or {}).get("coupling_offsets", {})
    C = robot.coupling_joint
    gain_of = dict(zip(input_rows(robot), robot.gains)) if robot.gains is not None else {}
    rows = []
    for b in robot.bodies:
        parent = BASE if b.parent < 0 else robot.bodies[b.parent].name
        if b.convention == "urdf":
            v = [float(ext[i]) for i in b.rows[:6]]
            rows.append({"name": b.name, "parent": parent, "type": "transform", "xyz": v[:3], "rpy": v[3:]})
            continue
        v = [float(ext[i]) for i in b.rows]
        k = b.conv.joint_row_index(b.kind)
        if b.name in offsets and k is not None:
            v[k] -= offsets[b.name]
        row = [b.name, parent, {0: "R", 1: "P", 2: "F"}[b.kind]] + v
        if robot.gains is not None:
            row.append(float(a[gain_of[b.name]]) if b.name in gain_of else None)
        rows.append(row)
    cols = ["name", "parent", "type", *letters] + (["K"] if robot.gains is not None else [])
    doc = {"name": robot.name, "convention": table_conv, "units": {"length": "m", "angle": "rad"}, "columns": cols,
           "joints": rows, "tip": robot.bodies[robot.tip].name, "joint_names": list(robot.joint_names),
           "home": robot.home_np.tolist(), "q_min": robot.q_min.tolist(), "q_max": robot.q_max.tolist()}
    if C is not None:
        doc["coupling"] = coupling_dict(robot, offsets)
    return doc


def input_rows(robot) -> list[str]:
    """Name of the body each input drives directly (C row = unit vector there; without C, inputs == (k,))."""
    C = robot.coupling_joint
    out = []
    for k in range(robot.n_inputs):
        hits = [b.name for b in robot.bodies if b.inputs and (
            b.inputs[0] == k if C is None else (C[b.inputs[0], k] == 1.0 and np.count_nonzero(C[b.inputs[0]]) == 1))]
        if not hits:
            raise RobotFileError(f"robot {robot.name!r}: input {robot.joint_names[k]!r} drives no body directly")
        out.append(hits[0])
    return out


def coupling_dict(robot, offsets=None) -> dict:
    """The `coupling` mapping of a robot with Cj: each coupled body's sources (input names) and offset."""
    C, offsets = robot.coupling_joint, offsets or {}
    independent = input_rows(robot)
    out = {}
    for b in robot.bodies:
        if not b.inputs or b.name in independent:
            continue
        terms = {independent[k]: float(c) for k, c in enumerate(C[b.inputs[0]]) if c != 0.0}
        terms["offset"] = float(offsets.get(b.name, 0.0))
        out[b.name] = terms
    return out
