"""Robot files: YAML tables in each seed's own layout, read and written.

PRY (seed 000 Table 6.1):                 MDH (seed 001 Table 1):
    convention: pry                           convention: mdh
    units: {length: m, angle: deg}            units: {length: m, angle: rad}
    base: [0, 0, 0.8]                         columns: [sigma, alpha, d, theta, r, beta, K]
    columns: [x, y, z, pitch, roll, yaw, type]  frames:
    joints:                                     - [2, 0, 0, 1.5708, 0.5, 0, 0]
      - [0.5, 0, -0.15, 0, 0, 0, revolute]      - ...

MCPC (seed 004 Table 4.1):
    convention: mcpc
    columns: [a1, a2, a3, d1, d2, d3, predecessor, closure, type]
    rows:
      - [0, 0, 0, 0, 0, 0, 0, 0, 3]

DH tables with a named convention (`convention: standard_dh | craig_mdh | khalil_kleinfinger`), a
parent column, fixed 6-D transform rows and joint coupling: see `jaxcal.robots.table`. `convention:
mdh` keeps the seed 001 layout above (Khalil-Kleinfinger letters, sigma column); a file with `frames:`
and no `convention` is read that way too. The UR ROS driver's kinematics YAML (`kinematics:` or
`dh_parameters:`) is recognised by its keys: see `jaxcal.robots.ur`.

In the seed 001 layout, `coupling: {Cm: [[...]], Cj: [[...]]}` gives the (n x n) motor and joint
coupling matrices of seed 001 eq 4, q = Cj diag(K) Cm qm + Offset (n moving frames, sigma 0 or 1, in
frame order; either may be left out: the identity). The offsets are the theta (sigma 0) / r (sigma 1)
column and the gains the K column.

Optional keys: name, home, q_min, q_max, joint_names, actuated (mcpc), tip (mcpc), closure_start (mcpc:
the free-joint start of the closure, see docs/closure.md). Errors name
the file, the row and the field. A key given twice, a top-level key that looks like a misspelt known
key (`joint_name`), and a joint name given twice are errors too; other extra keys are ignored.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import yaml

from jaxcal.kin.conventions import PRY_KINDS
from jaxcal.names import closest, duplicates
from jaxcal.robots.build import mcpc_robot, mdh_robot, pry_robot
from jaxcal.robots.errors import RobotFileError
from jaxcal.robots.table import TABLE_CONVENTIONS, table_dict, table_robot
from jaxcal.robots.ur import is_ur_kinematics, robot_from_ur, ur_dict
from jaxcal.robots.urdf import load_urdf, save_urdf
from jaxcal.robots.urdf_write import robot_urdf_text
from jaxcal.textfile import read_bytes
from jaxcal.yamlfile import load_yaml

_COLUMNS = {
    "pry": ["x", "y", "z", "pitch", "roll", "yaw", "type"],
    "mdh": ["sigma", "alpha", "d", "theta", "r", "beta", "K"],
    "mcpc": ["a1", "a2", "a3", "d1", "d2", "d3", "predecessor", "closure", "type"],
}
_ROWS_KEY = {"pry": "joints", "mdh": "frames", "mcpc": "rows"}
KNOWN_KEYS = ("name", "convention", "units", "base", "columns", "joints", "frames", "rows", "home", "q_min", "q_max",
              "joint_names", "actuated", "tip", "closure_start", "free", "description", "coupling")
CONVENTIONS = tuple(sorted(set(_COLUMNS) | set(TABLE_CONVENTIONS)))
_TYPE_LETTERS = {"R": "revolute", "P": "prismatic", "C": "cylindrical", "U": "universal", "S": "spherical", "F": "fixed"}


def _angle_scale(doc, path):
    unit = (doc.get("units") or {}).get("angle", "rad")
    if unit not in ("rad", "deg"):
        raise RobotFileError(f"{path}: units.angle must be 'rad' or 'deg', got {unit!r}")
    return np.pi / 180.0 if unit == "deg" else 1.0


def _length_scale(doc, path):
    unit = (doc.get("units") or {}).get("length", "m")
    if unit not in ("m", "mm"):
        raise RobotFileError(f"{path}: units.length must be 'm' or 'mm', got {unit!r}")
    return 1e-3 if unit == "mm" else 1.0


def _number(value, path, row, field):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise RobotFileError(f"{path}, row {row}, field '{field}': not a number: {value!r}") from None
    if not np.isfinite(v):
        raise RobotFileError(f"{path}, row {row}, field '{field}': non-finite value {value!r}")
    return v


def _rows(doc, conv, path):
    key = _ROWS_KEY[conv]
    rows = doc.get(key)
    if not isinstance(rows, list) or not rows:
        raise RobotFileError(f"{path}: '{key}' must be a non-empty list of rows {_COLUMNS[conv]}")
    cols = _COLUMNS[conv]
    for i, row in enumerate(rows, start=1 if conv != "mdh" else 0):
        if not isinstance(row, (list, tuple)) or len(row) != len(cols):
            n = len(row) if isinstance(row, (list, tuple)) else "not a list"
            raise RobotFileError(f"{path}, row {i}: expected {len(cols)} fields {cols}, got {n}")
    return rows


def _check_keys(doc: dict, path: str) -> None:
    """A top-level key close to a known one but not it (a typo) and a joint name given twice are errors."""
    for key in doc:
        if key not in KNOWN_KEYS:
            near = closest(str(key), KNOWN_KEYS, n=1)
            if near:
                raise RobotFileError(f"{path}: unknown key {key!r} (did you mean {near[0]!r}?)")
    names = doc.get("joint_names")
    if names is not None:
        if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
            raise RobotFileError(f"{path}: field 'joint_names' must be a list of non-empty names, got {names!r}")
        dup = duplicates(names)
        if dup:
            raise RobotFileError(f"{path}: field 'joint_names': name {dup[0]!r} given twice; joint names must be unique")


def _convention(doc, path) -> str:
    """The file's convention; a file with `frames:` and none is the seed 001 (Khalil-Kleinfinger) layout."""
    conv = doc.get("convention")
    if conv is None and "frames" in doc:
        return "mdh"
    if conv not in CONVENTIONS:
        near = closest(str(conv), CONVENTIONS, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise RobotFileError(f"{path}: field 'convention': unknown convention {conv!r}{hint}; expected one of {list(CONVENTIONS)}")
    return conv


def _mdh_coupling(doc, path, n: int) -> dict:
    """Cm and Cj of the seed 001 layout's `coupling` mapping as `mdh_robot` keywords."""
    spec = doc.get("coupling")
    if spec is None:
        return {}
    if not isinstance(spec, dict) or not spec or set(spec) - {"Cm", "Cj"}:
        raise RobotFileError(f"{path}: field 'coupling' (seed 001 layout) must be a mapping with keys Cm and/or Cj, "
                             f"each an {n} x {n} matrix (one row and column per moving frame)")
    out = {}
    for key, kw in (("Cm", "coupling_motor"), ("Cj", "coupling_joint")):
        if key not in spec:
            continue
        rows = spec[key]
        if not isinstance(rows, list) or len(rows) != n or not all(isinstance(r, list) and len(r) == n for r in rows):
            raise RobotFileError(f"{path}, field 'coupling', {key}: expected an {n} x {n} matrix (list of {n} rows of {n} numbers)")
        try:
            C = np.array(rows, dtype=float)
        except (TypeError, ValueError):
            raise RobotFileError(f"{path}, field 'coupling', {key}: not a matrix of numbers: {rows!r}") from None
        if not np.all(np.isfinite(C)):
            raise RobotFileError(f"{path}, field 'coupling', {key}: non-finite entry")
        out[kw] = C
    return out


def robot_from_dict(doc: dict, path: str = "<dict>", lines=None):
    """Build a robot from a parsed YAML document (`lines`: the file line of each row of a DH table)."""
    if not isinstance(doc, dict):
        raise RobotFileError(f"{path}: expected a mapping at the top level")
    name = str(doc.get("name", os.path.splitext(os.path.basename(path))[0]))
    if is_ur_kinematics(doc):
        return robot_from_ur(doc, path, name)
    _check_keys(doc, path)
    conv = _convention(doc, path)
    if conv in TABLE_CONVENTIONS:
        try:
            return table_robot({**doc, "convention": conv}, path, lines, name)
        except RobotFileError:
            raise
        except ValueError as exc:
            raise RobotFileError(f"{path}: {exc}") from None
    ang, lng = _angle_scale(doc, path), _length_scale(doc, path)
    rows = _rows(doc, conv, path)
    common = {k: doc[k] for k in ("home", "q_min", "q_max", "joint_names") if k in doc}
    try:
        if conv == "pry":
            base = [_number(v, path, "base", "base") * lng for v in doc.get("base", [0, 0, 0])]
            modules = []
            for i, row in enumerate(rows, start=1):
                kind = _TYPE_LETTERS.get(str(row[6]), str(row[6]))
                if kind not in PRY_KINDS:
                    raise RobotFileError(f"{path}, row {i}, field 'type': unknown joint type {row[6]!r}")
                b = [_number(row[k], path, i, _COLUMNS[conv][k]) * lng for k in range(3)]
                pry = [_number(row[k], path, i, _COLUMNS[conv][k]) * ang for k in range(3, 6)]
                modules.append((kind, b, pry))
            return pry_robot(name, base, modules, **common)
        if conv == "mdh":
            frames = []
            for j, row in enumerate(rows):
                vals = [_number(v, path, j, f) for v, f in zip(row, _COLUMNS[conv])]
                sigma = int(vals[0])
                frames.append((sigma, vals[1] * ang, vals[2] * lng, vals[3] * ang, vals[4] * lng, vals[5] * ang, vals[6]))
            coupling = _mdh_coupling(doc, path, sum(f[0] in (0, 1) for f in frames))
            return mdh_robot(name, frames, **common, **coupling)
        table = []
        for i, row in enumerate(rows, start=1):
            vals = [_number(v, path, i, f) for v, f in zip(row, _COLUMNS[conv])]
            table.append([vals[0] * ang, vals[1] * ang, vals[2] * ang, vals[3] * lng, vals[4] * lng, vals[5] * lng,
                          int(vals[6]), int(vals[7]), int(vals[8])])
        extra = {k: doc[k] for k in ("actuated", "tip", "closure_start") if k in doc}
        return mcpc_robot(name, table, **common, **extra)
    except RobotFileError:
        raise
    except ValueError as exc:  # builder errors name the row; add the file
        raise RobotFileError(f"{path}: {exc}") from None


def load_robot(path: str, **kwargs):
    """Load a robot from YAML (seed table layouts) or URDF (`base=`, `tip=` link names)."""
    if str(path).lower().endswith(".urdf"):
        return load_urdf(path, **kwargs)
    raw = read_bytes(path, RobotFileError)
    try:
        doc = load_yaml(raw)
    except yaml.YAMLError as exc:
        raise RobotFileError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    return robot_from_dict(doc, path, row_lines(raw, "joints"))


def row_lines(raw, key: str) -> list[int] | None:
    """1-based file line of each item of the top-level list `key` (None when there is none)."""
    try:
        node = yaml.compose(raw, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None
    if not isinstance(node, yaml.MappingNode):
        return None
    for k, v in node.value:
        if getattr(k, "value", None) == key and isinstance(v, yaml.SequenceNode):
            return [item.start_mark.line + 1 for item in v.value]
    return None


def robot_to_dict(robot, a=None) -> dict:
    """The YAML document of a robot built from a seed table (with parameters a, default nominal).

    Angles are written in radians and lengths in metres.
    """
    source = robot.extras.get("source_format")
    if source == "ur_kinematics":
        return ur_dict(robot, a, robot.extras.get("ur_form", "kinematics"))
    if "table" in robot.extras or robot.bodies[0].convention not in _COLUMNS:
        return table_dict(robot, a)
    a = np.asarray(robot.nominal_np if a is None else a, float)
    conv = robot.bodies[0].convention
    ext = np.append(a, 0.0)
    doc = {"name": robot.name, "convention": conv, "units": {"length": "m", "angle": "rad"},
           "columns": _COLUMNS[conv], "home": robot.home_np.tolist(), "q_min": robot.q_min.tolist(),
           "q_max": robot.q_max.tolist(), "joint_names": list(robot.joint_names)}
    rows = []
    if conv == "pry":
        doc["base"] = np.asarray(robot.base.p).tolist()
        for b in robot.bodies:
            rows.append([float(ext[i]) for i in b.rows] + [b.kind])
    elif conv == "mdh":
        gains = dict(zip([b for b in robot.bodies if b.inputs], robot.gains or ()))
        for b in robot.bodies:
            al, d, th, r, be = (float(ext[i]) for i in b.rows)
            k = float(a[gains[b]]) if b in gains else 0.0
            rows.append([int(b.kind), al, d, th, r, be, k])
        coupling = {key: np.asarray(C).tolist() for key, C in (("Cm", robot.coupling_motor), ("Cj", robot.coupling_joint))
                    if C is not None}
        if coupling:
            doc["coupling"] = coupling
    else:
        pairs = getattr(robot.closure, "pairs", ())
        closures = {q: p for p, q, _ in pairs}  # closure column on the row that names its partner
        if pairs:
            doc["closure_start"] = [float(s) for s in robot.closure.start]
        for i, b in enumerate(robot.bodies, start=1):
            rows.append([float(ext[k]) for k in b.rows] + [b.parent + 1, int(closures.get(i, 0)), int(b.kind)])
        doc["actuated"] = [i for i, b in enumerate(robot.bodies, start=1) if b.inputs]
        doc["tip"] = robot.tip + 1
    doc[_ROWS_KEY[conv]] = rows
    return doc


def save_robot(robot, path: str, a=None) -> str:
    """Write the robot (with parameters a) as YAML atomically (temp file, then rename): the layout it
    was read in (seed table, DH table, UR kinematics). A path ending in ".urdf" writes the calibrated
    URDF of a URDF-loaded robot (`jaxcal.robots.urdf.save_urdf`) or a new URDF of any other robot
    (`jaxcal.robots.urdf_write.robot_urdf_text`)."""
    if str(path).lower().endswith(".urdf"):
        if "urdf_text" in robot.extras:
            return save_urdf(robot, path, a)
        return _write_text(robot_urdf_text(robot, a), path, ".urdf.tmp")
    if "urdf_text" in robot.extras and "source_format" not in robot.extras:
        raise RobotFileError(f"{path}: a robot loaded from a URDF is saved as .urdf, not YAML")
    text = yaml.safe_dump(robot_to_dict(robot, a), sort_keys=False, default_flow_style=None)
    return _write_text(text, path, ".yaml.tmp")


def _write_text(text: str, path: str, suffix: str) -> str:
    """Write text atomically (temp file in the same folder, then rename)."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=suffix)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)
    return path
