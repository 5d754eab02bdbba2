"""CSV measurement files: column layout, units, unit-mistake checks, precise errors.

Layout (see docs/file-formats.md): one header row, one row per sample.
- joints: columns named after the robot's joints (or given with `joints=`); revolute joints in the
  angle unit, prismatic joints (`prismatic=`) in the length unit;
- position of marker k: `x, y, z` (one marker) or `xk, yk, zk` (FIGAROH: `x1, y1, z1, x2, ...`);
- optional orientation of marker k: roll-pitch-yaw angles `phixk, phiyk, phizk` (FIGAROH's
  columns; fixed-axis X-Y-Z as URDF and pinocchio: R = Rz(phiz) Ry(phiy) Rx(phix)), a rotation
  vector `rvxk, rvyk, rvzk`, a unit quaternion `qwk, qxk, qyk, qzk`, or a rotation matrix
  `r11 .. r33` (single marker);
- optional covariates: `time` (or `t`), `temperature`, `direction`, and any named with `covariates=`.
Units: lines starting with `#` before the header may say `# units: length=mm, angle=deg` and
`# prismatic: j3` (joint columns that are lengths); arguments give them otherwise; default m and
rad. Orientation angles use the angle unit.
Text: UTF-8 (a byte-order mark is skipped), any line ending; other bytes, NUL bytes and broken
quoting are errors naming the line.
"""

from __future__ import annotations

import csv
import dataclasses
import re
import warnings

import numpy as np

from jaxcal.textfile import read_bytes

LENGTH_SCALE = {"m": 1.0, "mm": 1e-3}
ANGLE_SCALE = {"rad": 1.0, "deg": np.pi / 180.0}
COVARIATE_ALIASES = {"time": "time", "t": "time", "temperature": "temperature", "temp": "temperature",
                     "direction": "direction"}
_POS = re.compile(r"^([xyz])(\d*)$")
_RPY = re.compile(r"^phi([xyz])(\d*)$")
_ROTVEC = re.compile(r"^rv([xyz])(\d*)$")
_QUAT = re.compile(r"^q([wxyz])(\d*)$")
_MATRIX = re.compile(r"^r([123])([123])$")
_UNITS = re.compile(r"\b(length|angle)\s*[=:]\s*([a-z]+)", re.IGNORECASE)
_PRISMATIC = re.compile(r"^#\s*prismatic\s*:\s*(.*)$", re.IGNORECASE)
MAX_POSITION_M = 20.0  # |p| beyond this in metres is taken for millimetres given as metres
MIN_POSITION_MM = 5.0  # every |p| below this in millimetres looks like metres given as millimetres
MAX_ANGLE_RAD = 2 * np.pi + 0.5  # |q| beyond this in radians is taken for degrees given as radians
MAX_PRISMATIC_M = 20.0  # a prismatic joint reading beyond this in metres is taken for millimetres given as metres
LIMIT_FACTOR = 3.0  # readings this many times beyond the robot's limits that fit them in the other unit: a unit mistake


def prismatic_joints(robot) -> tuple[str, ...]:
    """Names of the robot's prismatic joint inputs: their CSV values are lengths, not angles. With a
    coupling matrix Cj (body inputs index the joint variables qj = Cj q), an input is prismatic when the
    joint variables it drives are prismatic."""
    C = robot.coupling_joint
    out = []
    for body in robot.bodies:
        if body.conv.is_prismatic(body.kind) and len(body.inputs) == 1:
            if C is None:
                out.append(robot.joint_names[body.inputs[0]])
            else:
                out += [robot.joint_names[k] for k in np.flatnonzero(C[body.inputs[0]]) if robot.joint_names[k] not in out]
    return tuple(out)


def joint_limits(robot) -> dict:
    """{joint name: (lower, upper)} of the robot's joint inputs with finite limits (SI: rad, m)."""
    lo, hi = np.asarray(robot.q_min, float), np.asarray(robot.q_max, float)
    return {n: (float(a), float(b)) for n, a, b in zip(robot.joint_names, lo, hi) if np.isfinite(a) and np.isfinite(b) and a < b}


def at(path: str, line) -> str:
    """Where a row is, for messages: `path, line 7` for a text line number, `path, <label>` for a labelled row
    (a spreadsheet's `row 17`)."""
    return f"{path}, {line}" if isinstance(line, str) else f"{path}, line {line}"


class DataError(ValueError):
    """Bad input data; the message names the file, row, column or sample."""


class DataWarning(UserWarning):
    """Data that can be used but probably not as intended (a constant joint column, a unit that looks wrong)."""


class UnitWarning(DataWarning):
    """Values that look like they are in another unit than the one stated (possible but unlikely)."""


@dataclasses.dataclass
class Table:
    """Raw numbers of a CSV file with the physical line number of every row."""

    path: str
    header: list[str]
    values: np.ndarray  # (N, n_columns) float
    lines: np.ndarray  # (N,) 1-based line numbers
    units: dict  # from the header comment: {"length": ..., "angle": ...}
    text: tuple = ()  # (N,) the rows' fields as read, for text columns (a session label)

    def column_text(self, name: str) -> np.ndarray:
        """The raw text of one column, (N,) strings."""
        c = self.header.index(name)
        return np.array([row[c] for row in self.text], dtype=str)


def _header_units(comment: str, path: str, lineno: int) -> dict:
    """{"length": .., "angle": ..} from a `# units:` line, or {"prismatic": [names]} from a `# prismatic:` line."""
    m = _PRISMATIC.match(comment)
    if m:
        return {"prismatic": [n.strip() for n in m.group(1).split(",") if n.strip()]}
    out = {}
    for key, unit in _UNITS.findall(comment):
        key, unit = key.lower(), unit.lower()
        allowed = LENGTH_SCALE if key == "length" else ANGLE_SCALE
        if unit not in allowed:
            raise DataError(f"{path}, line {lineno}: {key} unit must be one of {sorted(allowed)}, got {unit!r}")
        out[key] = unit
    return out


def decode_text(raw: bytes, path: str) -> str:
    """The text of a file's bytes: UTF-8 with an optional byte-order mark; other bytes and NUL bytes
    are a DataError naming the line."""
    nul = raw.find(b"\x00")
    if nul >= 0:
        line = raw.count(b"\n", 0, nul) + 1
        raise DataError(f"{path}, line {line}: NUL byte in the file: not a text CSV file")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise DataError(f"{path}, line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); save the file as UTF-8") from None


def read_text(path: str) -> str:
    """A text file's content (see `decode_text`); a missing or unreadable file is a DataError."""
    return decode_text(read_bytes(path, DataError), path)


def _fields(line: str, delimiter: str, path: str, lineno: int) -> list[str]:
    """The stripped fields of one CSV line; broken quoting is a DataError naming the line."""
    try:
        rows = list(csv.reader([line], delimiter=delimiter, strict=True))
    except csv.Error as exc:
        raise DataError(f"{path}, line {lineno}: not a CSV row ({exc})") from None
    return [f.strip() for f in (rows[0] if rows else [])]


def read_table(path: str, delimiter: str = ",", needed=None, header_only: bool = False) -> Table:
    """All rows as numbers. Errors name the file, the 1-based line and the column.

    Only the columns in `needed` (default all) must hold numbers; the others may hold any text.
    header_only: stop after the header (values empty), to check the columns before the rows.
    """
    path = str(path)
    text_lines = read_text(path).splitlines()
    units, header, header_line = {}, None, 0
    rows, lines = [], []
    for lineno, line in enumerate(text_lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            if header is None:
                units.update(_header_units(stripped, path, lineno))
            continue
        fields = _fields(line, delimiter, path, lineno)
        if header is None:
            header, header_line = fields, lineno
            dup = sorted({h for h in header if header.count(h) > 1})
            if dup:
                raise DataError(f"{path}, line {lineno}: duplicate column name(s) {dup}")
            if header_only:
                return Table(path, header, np.zeros((0, len(header))), np.zeros(0, int), units)
            continue
        if len(fields) != len(header):
            raise DataError(f"{path}, line {lineno}: {len(fields)} fields, header has {len(header)}")
        rows.append(fields)
        lines.append(lineno)
    if header is None:
        raise DataError(f"{path}: empty file (no header row)")
    if not rows:
        raise DataError(f"{path}: no data rows after the header on line {header_line}")
    needed = set(header if needed is None else needed)
    values = np.full((len(rows), len(header)), np.nan)
    for r, (fields, lineno) in enumerate(zip(rows, lines)):
        for c, (name, text) in enumerate(zip(header, fields)):
            if name not in needed:
                continue
            try:
                v = float(text)
            except ValueError:
                raise DataError(f"{path}, line {lineno}, column {name!r}: not a number: {text!r}") from None
            if not np.isfinite(v):
                raise DataError(f"{path}, line {lineno}, column {name!r}: non-finite value {text!r}")
            values[r, c] = v
    return Table(path, header, values, np.asarray(lines), units, tuple(rows))


def resolve_unit(kind: str, argument, from_file, path: str) -> str:
    """The unit of `kind` ("length"/"angle"): the argument, else the file's header, else SI."""
    allowed = LENGTH_SCALE if kind == "length" else ANGLE_SCALE
    if argument is not None and argument not in allowed:
        raise DataError(f"{path}: {kind}_unit must be one of {sorted(allowed)}, got {argument!r}")
    if argument is not None and from_file is not None and argument != from_file:
        raise DataError(f"{path}: the header says {kind}={from_file} but {kind}_unit={argument!r} was given")
    return argument or from_file or ("m" if kind == "length" else "rad")


SESSION_COLUMN = "session"  # a column of this name (any case) labels each row's measurement session

# Readings of instruments that give neither a point nor a pose, one column each, with the unit kind of the column:
# the theodolite's sight angles and the range of a total station or a laser range finder (`Dataset.from_csv`).
INSTRUMENT_COLUMNS = {
    "theodolite": (("azimuth", "angle"), ("elevation", "angle")),
    "theodolite_range": (("azimuth", "angle"), ("elevation", "angle"), ("range", "length")),
    "laser_range": (("range", "length"),),
}


@dataclasses.dataclass
class Layout:
    """Which columns hold what."""

    joints: list[str]
    position: list[str]
    orientation: str | None  # "rpy" | "rotvec" | "quaternion" | "matrix" | None
    orientation_columns: list[str]
    covariates: dict  # canonical name -> column
    markers: list[str]  # marker ids found ("" for plain x, y, z)
    session: str | None = None  # the column of text session labels (`measure.sessions`), if any


def _markers(header):
    found = {}
    for h in header:
        m = _POS.match(h)
        if m:
            found.setdefault(m.group(2), set()).add(m.group(1))
    return sorted((k for k, v in found.items() if v == {"x", "y", "z"}), key=lambda k: int(k or 0))


def _orientation_columns(header, marker):
    rpy = [f"phi{a}{marker}" for a in "xyz"]
    if all(c in header for c in rpy):
        return "rpy", rpy
    rv = [f"rv{a}{marker}" for a in "xyz"]
    if all(c in header for c in rv):
        return "rotvec", rv
    qt = [f"q{a}{marker}" for a in "wxyz"]
    if all(c in header for c in qt):
        return "quaternion", qt
    mx = [f"r{i}{j}" for i in "123" for j in "123"]
    if all(c in header for c in mx):
        return "matrix", mx
    return None, []


def _is_measurement(h):
    return bool(_POS.match(h) or _RPY.match(h) or _ROTVEC.match(h) or _QUAT.match(h) or _MATRIX.match(h))


def find_layout(header, path, joints=None, position_columns=None, marker=None, covariates=(), orientation=True) -> Layout:
    """Classify the header's columns; errors name the file and the missing columns."""
    markers = _markers(header)
    if position_columns is not None:
        position = list(position_columns)
        marker_id = ""
    else:
        if not markers:
            raise DataError(f"{path}: missing column(s) for the measured position: expected x, y, z "
                            f"or x1, y1, z1, ...; header has {header}")
        marker_id = markers[0] if marker is None else str(marker)
        if marker_id not in markers:
            if marker_id == "1" and markers == [""]:
                marker_id = ""
            else:
                raise DataError(f"{path}: marker {marker!r} not found; markers with x, y, z columns: "
                                f"{[m or '(unnumbered)' for m in markers]}")
        position = [f"{a}{marker_id}" for a in "xyz"]
    kind, ocols = _orientation_columns(header, marker_id) if orientation else (None, [])
    cov = {}
    for h in header:
        if h.lower() in COVARIATE_ALIASES:
            cov[COVARIATE_ALIASES[h.lower()]] = h
    for c in covariates:
        if c.lower() != SESSION_COLUMN:  # text labels, read apart (Layout.session)
            cov[COVARIATE_ALIASES.get(c.lower(), c)] = c
    session = next((h for h in header if h.lower() == SESSION_COLUMN), None)
    if joints is None:
        used = set(position) | set(ocols) | set(cov.values()) | {session}
        joints = [h for h in header if h not in used and not _is_measurement(h)]
        if not joints:
            raise DataError(f"{path}: no joint columns found; header has {header}")
    need = list(joints) + position + ocols + list(cov.values())
    missing = [c for c in need if c not in header]
    if missing:
        from jaxcal.names import closest

        near = {m: closest(m, [h for h in header if h not in need], n=1) for m in missing}
        hint = "; ".join(f"{m!r} misspelt as {near[m][0]!r}?" for m in missing if near[m])
        raise DataError(f"{path}: missing column(s) {missing}; header has {header}" + (f" ({hint})" if hint else ""))
    return Layout(list(joints), position, kind, ocols, cov, markers, session)


def rotations_from_columns(kind, block, lines, path, angle_scale):
    """(N, 3, 3) rotation matrices from the orientation columns; errors name the line."""
    from scipy.spatial.transform import Rotation

    if kind == "rpy":
        rpy = block * angle_scale
        big = np.abs(rpy).max(axis=1) > MAX_ANGLE_RAD
        if big.any():
            i = int(np.flatnonzero(big)[0])
            raise DataError(f"{at(path, lines[i])}: roll/pitch/yaw angle of {np.abs(rpy[i]).max():.3g} rad: "
                            "degrees given as radians? state the angle unit")
        return Rotation.from_euler("xyz", rpy).as_matrix()  # lower case: fixed axes, R = Rz Ry Rx
    if kind == "rotvec":
        rv = block * angle_scale
        big = np.linalg.norm(rv, axis=1) > 2 * MAX_ANGLE_RAD
        if big.any():
            i = int(np.flatnonzero(big)[0])
            raise DataError(f"{at(path, lines[i])}: rotation vector of norm {np.linalg.norm(rv[i]):.3g} rad: "
                            "degrees given as radians? state the angle unit")
        return Rotation.from_rotvec(rv).as_matrix()
    if kind == "quaternion":
        norm = np.linalg.norm(block, axis=1)
        bad = np.abs(norm - 1.0) > 1e-3
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(f"{at(path, lines[i])}: quaternion (qw, qx, qy, qz) has norm {norm[i]:.6g}, expected 1")
        return Rotation.from_quat(block[:, [1, 2, 3, 0]]).as_matrix()
    R = block.reshape(-1, 3, 3)
    err = np.linalg.norm(np.swapaxes(R, 1, 2) @ R - np.eye(3), axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > 1e-3) | (det < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DataError(f"{at(path, lines[i])}: r11..r33 is not a rotation matrix (|R^T R - I| = {err[i]:.3g}, det {det[i]:.3g})")
    U, _, Vt = np.linalg.svd(R)  # project onto SO(3)
    return U @ Vt


def joint_scale(joints, prismatic, length_unit, angle_unit) -> np.ndarray:
    """Factor from the file's unit to SI per joint column: length unit for prismatic joints, angle unit otherwise."""
    return np.array([LENGTH_SCALE[length_unit] if j in prismatic else ANGLE_SCALE[angle_unit] for j in joints])


def check_joint_units(q, joints, lines, angle_unit, path, prismatic=()):
    """Joint values q in the stated unit. Degrees given as radians: |q| well beyond 2 pi is an
    error naming the column and line; radians given as degrees (every |q| below pi degrees) is a warning."""
    for j, name in enumerate(joints):
        if name in prismatic:
            continue
        col = np.abs(q[:, j])
        if angle_unit == "rad" and col.max() > MAX_ANGLE_RAD:
            i = int(np.argmax(col))
            raise DataError(f"{at(path, lines[i])}, column {name!r}: {q[i, j]:.6g} rad is more than a full turn: "
                            "degrees given as radians (or millimetres for a prismatic joint)? "
                            "state the unit with angle_unit='deg', a '# units: angle=deg' header line or a column map's units")
    rev = [j for j, name in enumerate(joints) if name not in prismatic]
    q = q[:, rev]
    if angle_unit == "deg" and len(q) > 1 and q.size and np.abs(q).max() < np.pi and np.ptp(q, 0).max() > 0:
        warnings.warn(f"{path}: every joint value is below {np.pi:.3g} deg although the unit is deg: radians given as degrees?",
                      UnitWarning, stacklevel=3)


def check_prismatic_units(q, joints, lines, length_unit, path, prismatic=()):
    """Prismatic joint readings in metres beyond 20 m: millimetres given as metres (an error naming the column and line)."""
    for j, name in enumerate(joints):
        if name not in prismatic or length_unit != "m" or not len(q):
            continue
        col = np.abs(q[:, j])
        if col.max() > MAX_PRISMATIC_M:
            i = int(np.argmax(col))
            raise DataError(f"{at(path, lines[i])}, column {name!r}: prismatic joint reading {q[i, j]:.6g} m: "
                            "millimetres given as metres? state the unit with length_unit='mm', a '# units: length=mm' header line "
                            "or a column map's units")


def check_limit_units(q_si, joints, lines, path, limits, prismatic=()):
    """Readings (SI) far beyond the robot's joint limits that would fit them in the other unit (degrees read as
    radians: 57.3x; millimetres read as metres: 1000x) are an error naming the column and line.

    A column is refused when its largest excess over the limits is more than `LIMIT_FACTOR` times the limit's
    magnitude and every reading divided by the unit factor lies within the limits (10% margin); a small overshoot
    is left to the fit's health record (joint readings outside the limits)."""
    for j, name in enumerate(joints):
        if name not in limits or not len(q_si):
            continue
        lo, hi = limits[name]
        col = q_si[:, j]
        size = max(abs(lo), abs(hi))
        if np.abs(col).max() <= LIMIT_FACTOR * size:
            continue
        factor, unit = (1e3, "millimetres given as metres") if name in prismatic else (180.0 / np.pi, "degrees given as radians")
        margin = 0.1 * (hi - lo)
        scaled = col / factor
        if np.all((scaled >= lo - margin) & (scaled <= hi + margin)):
            i = int(np.argmax(np.abs(col)))
            si = "m" if name in prismatic else "rad"
            raise DataError(f"{at(path, lines[i])}, column {name!r}: reading {col[i]:.6g} {si} is "
                            f"{np.abs(col[i]) / size:.3g} times the joint limit [{lo:.4g}, {hi:.4g}] {si}, and every reading "
                            f"of the column fits the limits divided by {factor:.4g}: {unit}? state the unit")


def constant_columns(q, joints) -> list[str]:
    """Joint columns whose readings are all equal (their offsets cannot be identified); none for one sample."""
    if len(q) < 2:
        return []
    return [name for j, name in enumerate(joints) if np.ptp(q[:, j]) == 0]


def check_length_units(p_si, lines, length_unit, path):
    """Millimetres given as metres (|p| > 20 m): an error; metres given as millimetres (every
    |p| < 5 mm): a warning."""
    norm = np.linalg.norm(p_si, axis=1)
    if length_unit == "m" and norm.max() > MAX_POSITION_M:
        i = int(np.argmax(norm))
        raise DataError(f"{at(path, lines[i])}: measured point {norm[i]:.6g} m from the device origin: "
                        "millimetres given as metres? state the unit with length_unit='mm', a '# units: length=mm' header line "
                        "or a column map's units")
    if length_unit == "mm" and norm.max() < MIN_POSITION_MM * 1e-3:
        warnings.warn(f"{path}: every measured point is within {MIN_POSITION_MM} mm of the device origin although the "
                      "unit is mm: metres given as millimetres?", UnitWarning, stacklevel=3)


__all__ = ["DataError", "DataWarning", "INSTRUMENT_COLUMNS", "Layout", "Table", "UnitWarning", "at", "check_limit_units",
           "check_prismatic_units",
           "constant_columns", "decode_text", "find_layout", "joint_limits", "joint_scale", "prismatic_joints", "read_table",
           "read_text", "resolve_unit"]
