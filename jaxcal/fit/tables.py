"""Spreadsheets (.xlsx) and vendor text exports (laser trackers, motion capture) read through a column map.

A column map (a dict, or a YAML file holding one) says which file column is which quantity, the unit of
each column and the angle convention of the orientation (docs/file-formats.md, "Spreadsheets and vendor
exports"):

    joints: {j1: "A1 [deg]", j2: "A2 [deg]"}       # joint name -> column; or a list of columns in q order
    position: {x: "X [mm]", y: "Y [mm]", z: "Z [mm]"}  # or a list of three columns
    orientation: {form: euler, sequence: ZYX, columns: ["Rz", "Ry", "Rx"]}
    units: {Rz: deg, Ry: deg, Rx: deg}              # per column; else the header's "[mm]" / "(deg)" suffix
    session: Session                                # text or numbers, kept as strings
    covariates: {temperature: "T [C]"}              # numbers
    sheet: Data                                     # .xlsx: the sheet (default the first)
    header_row: 3                                   # 1-based; default detected
    delimiter: ";"                                  # text: default detected among tab, ';' and ','

Orientation forms: `quaternion_xyzw`, `quaternion_wxyz` (unit quaternions, columns in that order),
`rotation_vector` (axis times angle), `matrix` (r11 .. r33 row by row) and `euler` with a `sequence` of
three axes: upper case for intrinsic (rotating) axes, R = R_a(t1) R_b(t2) R_c(t3) for "ABC"; lower case
for extrinsic (fixed) axes, R = R_c(t3) R_b(t2) R_a(t1) for "abc"; the columns give t1, t2, t3 in order.
Units: m, mm, cm, in for lengths, rad, deg for angles; a column without one takes the reader's default
(SI unless given). Without a map, the column names less their unit suffix follow the CSV layout
(`jaxcal.fit.csvfile`). Errors name the file, the sheet, the cell (`B17`) or line, and the column.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
import re
import warnings

import numpy as np

from jaxcal.fit import csvfile as cf
from jaxcal.fit.csvfile import DataError
from jaxcal.names import suggestion
from jaxcal.textfile import read_bytes

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254}
ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}
FORMS = {"quaternion_xyzw": 4, "quaternion_wxyz": 4, "rotation_vector": 3, "euler": 3, "matrix": 9}
MAP_KEYS = ("joints", "position", "orientation", "units", "session", "covariates", "sheet", "header_row", "delimiter")
DELIMITERS = ("\t", ";", ",")  # tried in this order: decimal commas never make ',' the delimiter of a ';' file
WORKBOOK_SUFFIXES = (".xlsx", ".xlsm")
_SUFFIX = re.compile(r"^(?P<name>.*?)\s*[\[(](?P<unit>[^\[\]()]*)[\])]\s*$")


@dataclasses.dataclass(frozen=True)
class ColumnMap:
    """Which column holds what. Columns are header texts as written in the file."""

    joints: tuple  # joint columns in the order of q
    joint_names: tuple | None  # the joints' names (keys of a joints mapping); None: the columns less their unit suffix
    position: tuple  # x, y, z columns
    form: str | None = None  # orientation form (FORMS), None without orientation
    sequence: str | None = None  # euler axes
    orientation: tuple = ()
    units: dict = dataclasses.field(default_factory=dict)  # column -> unit named in the map
    session: str | None = None
    covariates: dict = dataclasses.field(default_factory=dict)  # name -> column
    sheet: str | None = None
    header_row: int | None = None
    delimiter: str | None = None

    def columns(self) -> list:
        """Every column the map names, each once, in map order."""
        cols = [*self.joints, *self.position, *self.orientation, *([self.session] if self.session else []),
                *self.covariates.values()]
        return list(dict.fromkeys(cols))


@dataclasses.dataclass
class Grid:
    """The cells of one sheet or text file: non-blank rows with their 1-based row (line) numbers."""

    path: str
    sheet: str | None  # None for a text file
    rows: list  # tuples of cell values (str, int, float, None, ...)
    numbers: list  # row or line number of each row
    decimal_comma: bool = False
    raw: bytes = b""  # a workbook's bytes, to explain empty formula cells

    def row_label(self, k):
        """A row for messages: `row 17` in a workbook, the line number in a text file."""
        return f"row {self.numbers[k]}" if self.sheet is not None else int(self.numbers[k])

    def cell(self, k, c, column) -> str:
        """`book.xlsx, sheet 'Data', cell B17, column 'X'` or `export.txt, line 12, column 'X'`."""
        if self.sheet is None:
            return f"{self.path}, line {self.numbers[k]}, column {column!r}"
        return f"{self.path}, sheet {self.sheet!r}, cell {column_letter(c)}{self.numbers[k]}, column {column!r}"


# -- units and rotations ---------------------------------------------------------------------------------
def split_unit(header: str) -> tuple[str, str | None]:
    """A header's name and its bracketed unit suffix: "X [mm]" -> ("X", "mm"), "A1 (deg)" -> ("A1", "deg")."""
    m = _SUFFIX.match(header)
    return (m.group("name"), m.group("unit").strip()) if m and m.group("name") else (header, None)


def unit_scale(unit: str, kind: str, where: str) -> float:
    """Factor from `unit` to SI for a quantity of `kind` ("length" or "angle"); errors name the place."""
    units = LENGTH_UNITS if kind == "length" else ANGLE_UNITS
    other = ANGLE_UNITS if kind == "length" else LENGTH_UNITS
    u = str(unit).strip().lower()
    if u in units:
        return units[u]
    if u in other:
        raise DataError(f"{where}: unit {unit!r} is not a{'n' if kind == 'angle' else ''} {kind}; expected one of {', '.join(units)}")
    raise DataError(f"{where}: unknown unit {unit!r}; expected one of {', '.join([*LENGTH_UNITS, *ANGLE_UNITS])}")


def unit_kind(unit: str, where: str) -> str:
    """"length" or "angle" for a known unit; an unknown unit is an error naming the place."""
    u = str(unit).strip().lower()
    if u in LENGTH_UNITS:
        return "length"
    if u in ANGLE_UNITS:
        return "angle"
    raise DataError(f"{where}: unknown unit {unit!r}; expected one of {', '.join([*LENGTH_UNITS, *ANGLE_UNITS])}")


def axis_rotations(axis: str, angles) -> np.ndarray:
    """(N, 3, 3) rotations by `angles` (rad) about the coordinate axis "x", "y" or "z"."""
    c, s = np.cos(angles), np.sin(angles)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.zeros((len(angles), 3, 3))
    R[:, "xyz".index(axis), "xyz".index(axis)] = 1.0
    R[:, i, i], R[:, j, j], R[:, i, j], R[:, j, i] = c, c, -s, s
    return R


def check_sequence(sequence, where: str) -> str:
    """An Euler sequence: three axes of x, y, z, no axis twice in a row, all upper case (intrinsic) or all lower (extrinsic)."""
    seq = str(sequence)
    ok = len(seq) == 3 and (seq.isupper() or seq.islower()) and set(seq.lower()) <= set("xyz")
    if not ok or seq[0] == seq[1] or seq[1] == seq[2]:
        raise DataError(f"{where}: Euler sequence must be three axes such as 'ZYX' (intrinsic, upper case) or 'xyz' "
                        f"(extrinsic, lower case), with no axis twice in a row; got {sequence!r}")
    return seq


def euler_matrices(angles, sequence: str) -> np.ndarray:
    """(N, 3, 3) rotations from (N, 3) angles (rad) about the axes of `sequence`: intrinsic (upper case)
    R = R1 R2 R3, extrinsic (lower case) R = R3 R2 R1, where Rk turns by angle k about axis k."""
    angles = np.asarray(angles, float)
    R = [axis_rotations(a, angles[:, k]) for k, a in enumerate(sequence.lower())]
    return R[0] @ R[1] @ R[2] if sequence.isupper() else R[2] @ R[1] @ R[0]


# -- the column map ----------------------------------------------------------------------------------------
def _columns(value, names, key, where) -> tuple:
    """Columns from a mapping {name: column} (in the order of `names`) or a list; errors name the key."""
    if isinstance(value, dict):
        missing = [n for n in names if n not in value]
        extra = [n for n in value if n not in names]
        if missing or extra:
            raise DataError(f"{where}: key {key!r} must map {', '.join(names)} to columns; "
                            f"missing {missing}, unknown {extra}")
        value = [value[n] for n in names]
    if not isinstance(value, list) or len(value) != len(names) or not all(isinstance(c, str) and c for c in value):
        raise DataError(f"{where}: key {key!r} must be {len(names)} column names ({', '.join(names)}), got {value!r}")
    return tuple(value)


def _orientation(doc, where):
    """(form, sequence, columns) of the map's orientation entry."""
    if not isinstance(doc, dict) or "form" not in doc or "columns" not in doc:
        raise DataError(f"{where}: key 'orientation' must be a mapping with 'form' and 'columns' (and 'sequence' for euler)")
    unknown = [k for k in doc if k not in ("form", "sequence", "columns")]
    if unknown:
        raise DataError(f"{where}: orientation: unknown key {unknown[0]!r}; known keys: form, sequence, columns")
    form = doc["form"]
    if form not in FORMS:
        raise DataError(f"{where}: orientation form {form!r} unknown{suggestion(str(form), FORMS)}; "
                        f"expected one of {', '.join(FORMS)}")
    cols = doc["columns"]
    if not isinstance(cols, list) or not all(isinstance(c, str) and c for c in cols):
        raise DataError(f"{where}: orientation columns must be a list of column names, got {cols!r}")
    if len(cols) != FORMS[form]:
        raise DataError(f"{where}: orientation form {form!r} takes {FORMS[form]} columns, got {len(cols)}: {cols}")
    if form == "euler":
        if "sequence" not in doc:
            raise DataError(f"{where}: orientation form 'euler' needs a 'sequence' such as 'ZYX' (intrinsic) or 'xyz' (extrinsic)")
        return form, check_sequence(doc["sequence"], f"{where}: orientation"), tuple(cols)
    if "sequence" in doc:
        raise DataError(f"{where}: orientation: 'sequence' applies to form 'euler' only, not {form!r}")
    return form, None, tuple(cols)


def parse_map(doc, where: str = "column map") -> ColumnMap:
    """A ColumnMap from its mapping form (module docstring); errors name the key."""
    if not isinstance(doc, dict):
        raise DataError(f"{where}: a column map is a mapping with keys {', '.join(MAP_KEYS)}, got {type(doc).__name__}")
    for key in doc:
        if key not in MAP_KEYS:
            raise DataError(f"{where}: unknown key {key!r}{suggestion(str(key), MAP_KEYS)}; known keys: {', '.join(MAP_KEYS)}")
    for key in ("joints", "position"):
        if key not in doc:
            raise DataError(f"{where}: key {key!r} missing: a column map names the joint and position columns")
    joints = doc["joints"]
    if isinstance(joints, dict) and joints:
        names, cols = tuple(str(n) for n in joints), _columns(joints, list(joints), "joints", where)
    elif isinstance(joints, list) and joints and all(isinstance(c, str) and c for c in joints):
        names, cols = None, tuple(joints)
    else:
        raise DataError(f"{where}: key 'joints' must be a mapping {{joint name: column}} or a list of columns, got {joints!r}")
    position = _columns(doc["position"], ["x", "y", "z"], "position", where)
    form, sequence, orientation = _orientation(doc["orientation"], where) if "orientation" in doc else (None, None, ())
    units = doc.get("units") or {}
    covariates = doc.get("covariates") or {}
    for key, value in (("units", units), ("covariates", covariates)):
        if not isinstance(value, dict) or not all(isinstance(v, str) and v for v in value.values()):
            raise DataError(f"{where}: key {key!r} must be a mapping of names to texts, got {value!r}")
    if "session" in covariates:
        raise DataError(f"{where}: covariates: give the session column with the key 'session', not as a covariate")
    session = doc.get("session")
    if session is not None and not (isinstance(session, str) and session):
        raise DataError(f"{where}: key 'session' must be a column name, got {session!r}")
    header_row = doc.get("header_row")
    if header_row is not None and (isinstance(header_row, bool) or not isinstance(header_row, int) or header_row < 1):
        raise DataError(f"{where}: key 'header_row' must be a row number >= 1, got {header_row!r}")
    delimiter = doc.get("delimiter")
    if delimiter is not None and delimiter not in DELIMITERS:
        raise DataError(f"{where}: key 'delimiter' must be one of {list(DELIMITERS)}, got {delimiter!r}")
    cmap = ColumnMap(cols, names, position, form, sequence, orientation, dict(units), session, dict(covariates),
                     None if doc.get("sheet") is None else str(doc["sheet"]), header_row, delimiter)
    measured = [*cmap.joints, *cmap.position, *cmap.orientation]
    unused = [c for c in units if c not in measured]
    if unused:
        raise DataError(f"{where}: units: column {unused[0]!r} is not a joint, position or orientation column of the map"
                        f"{suggestion(unused[0], measured)}")
    dup = [c for c in measured if measured.count(c) > 1]
    if dup:
        raise DataError(f"{where}: column {dup[0]!r} is mapped to two quantities")
    return cmap


def load_map(columns) -> ColumnMap:
    """A ColumnMap from a mapping or from the path of a YAML file holding one (errors name that file)."""
    if isinstance(columns, ColumnMap):
        return columns
    if isinstance(columns, dict):
        return parse_map(columns)
    import yaml

    from jaxcal.yamlfile import load_yaml

    path = os.fspath(columns)
    try:
        doc = load_yaml(cf.decode_text(read_bytes(path, DataError), path))
    except yaml.YAMLError as exc:
        raise DataError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    return parse_map(doc, path)


# -- reading cells -------------------------------------------------------------------------------------------
def column_letter(c: int) -> str:
    """The spreadsheet letters of the 0-based column c: 0 -> A, 25 -> Z, 26 -> AA."""
    out = ""
    c += 1
    while c:
        c, r = divmod(c - 1, 26)
        out = chr(65 + r) + out
    return out


def _blank(value) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def _trimmed(row) -> tuple:
    """A row without its trailing blank cells; text cells stripped."""
    row = [v.strip() if isinstance(v, str) else v for v in row]
    while row and _blank(row[-1]):
        row.pop()
    return tuple(row)


def read_workbook(path: str, sheet: str | None = None) -> Grid:
    """The cells of one sheet of an .xlsx workbook (by name, default the first), as last computed by the
    spreadsheet program for formulas; blank rows dropped."""
    import zipfile

    import openpyxl

    raw = read_bytes(path, DataError)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # openpyxl's notes on styles and extensions it does not read
            book = openpyxl.load_workbook(io.BytesIO(raw), data_only=True)
    except (zipfile.BadZipFile, KeyError, OSError, ValueError) as exc:
        hint = " (an old .xls workbook? save it as .xlsx)" if raw[:4] == b"\xd0\xcf\x11\xe0" else ""
        raise DataError(f"{path}: not an .xlsx workbook{hint}: {exc}") from None
    if sheet is None:
        ws = book.worksheets[0]
    elif sheet in book.sheetnames:
        ws = book[sheet]
    else:
        raise DataError(f"{path}: no sheet {sheet!r}{suggestion(sheet, book.sheetnames)}; sheets: {book.sheetnames}")
    rows, numbers = [], []
    for number, row in enumerate(ws.iter_rows(min_row=1, min_col=1, values_only=True), start=1):
        row = _trimmed(row)
        if row:
            rows.append(row)
            numbers.append(number)
    return Grid(path, ws.title, rows, numbers, raw=raw)


def _formulas(raw: bytes, sheet: str) -> dict:
    """{(row, column): formula} of a workbook's sheet (1-based row, 0-based column)."""
    import openpyxl

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ws = openpyxl.load_workbook(io.BytesIO(raw))[sheet]
    return {(cell.row, cell.column - 1): cell.value for row in ws.iter_rows() for cell in row
            if isinstance(cell.value, str) and cell.value.startswith("=")}


def detect_delimiter(lines) -> str:
    """The delimiter of a text export, from its last non-blank line (a data row): a tab if it holds one, else
    ';' if it holds one (numbers may then have decimal commas), else ','."""
    last = next((line for line in reversed(lines) if line.strip()), "")
    return next((d for d in DELIMITERS if d in last), ",")


def read_text_export(path: str, delimiter: str | None = None) -> Grid:
    """The fields of a delimited text export (tab, ';' or ','; detected unless given); blank lines dropped.
    With ';' numbers may use a decimal comma (`1234,5`)."""
    lines = cf.read_text(path).splitlines()
    delimiter = delimiter or detect_delimiter(lines)
    rows, numbers = [], []
    for number, line in enumerate(lines, start=1):
        try:
            fields = next(csv.reader([line], delimiter=delimiter, strict=True), [])
        except csv.Error as exc:
            raise DataError(f"{path}, line {number}: not a delimited row ({exc})") from None
        row = _trimmed(fields)
        if row:
            rows.append(row)
            numbers.append(number)
    return Grid(path, None, rows, numbers, decimal_comma=delimiter == ";")


def read_grid(path: str, sheet=None, delimiter=None) -> Grid:
    """A workbook's sheet (.xlsx, .xlsm) or a text export's fields."""
    if path.lower().endswith(WORKBOOK_SUFFIXES):
        return read_workbook(path, sheet)
    if sheet is not None:
        raise DataError(f"{path}: a sheet ({sheet!r}) was given, but this is a text file, not an .xlsx workbook")
    return read_text_export(path, delimiter)


def _is_number(value) -> bool:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return True
    try:
        float(str(value).replace(",", "."))
        return True
    except ValueError:
        return False


def _looks_like_header(grid: Grid, k: int) -> bool:
    """Every cell of row k is non-empty text, not a number, and the row below has no more cells."""
    row = grid.rows[k]
    texts = len(row) >= 2 and all(isinstance(v, str) and v and not _is_number(v) for v in row)
    return texts and (k + 1 == len(grid.rows) or len(grid.rows[k + 1]) <= len(row))


def header_index(grid: Grid, wanted, header_row=None) -> int:
    """Index of the header row: the row numbered `header_row`, else the first row holding every wanted
    column, else (no map) the first that looks like a header (`_looks_like_header`)."""
    where = f"{grid.path}" + (f", sheet {grid.sheet!r}" if grid.sheet is not None else "")
    word = "row" if grid.sheet is not None else "line"
    if header_row is not None:
        if header_row not in grid.numbers:
            raise DataError(f"{where}: header {word} {header_row} is blank or beyond the last {word}")
        return grid.numbers.index(header_row)
    if wanted:
        hits = [sum(c in row for c in wanted) for row in grid.rows]
        if hits and max(hits) == len(wanted):
            return hits.index(len(wanted))
        if not hits or max(hits) == 0:
            raise DataError(f"{where}: no row holds any column named in the column map ({list(wanted)}): another sheet, "
                            "or other column names?")
        return hits.index(max(hits))  # the closest row; the missing columns are reported against it
    for k in range(len(grid.rows)):
        if _looks_like_header(grid, k):
            return k
    raise DataError(f"{where}: no header row found (a row of column names); give header_row")


def check_header(header, wanted, where: str) -> None:
    """Every wanted column is in the header once; errors name the unknown columns and the closest header texts."""
    missing = [c for c in wanted if c not in header]
    if missing:
        hint = suggestion(missing[0], [h for h in header if isinstance(h, str)])
        raise DataError(f"{where}: unknown column(s) {missing} named in the column map{hint}; header has {list(header)}")
    dup = [c for c in wanted if list(header).count(c) > 1]
    if dup:
        raise DataError(f"{where}: column {dup[0]!r} appears twice in the header")


def cell_number(grid: Grid, k: int, c: int, column: str) -> float:
    """The number in row k, column c; an empty, non-numeric or non-finite cell is an error naming it."""
    row = grid.rows[k]
    value = row[c] if c < len(row) else None
    if _blank(value):
        formula = _formulas(grid.raw, grid.sheet).get((grid.numbers[k], c)) if grid.sheet is not None else None
        if formula:
            raise DataError(f"{grid.cell(k, c, column)}: formula {formula!r} has no saved value; open and save the "
                            "workbook in a spreadsheet program so that its results are stored")
        raise DataError(f"{grid.cell(k, c, column)}: empty cell")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        v = float(value)
    elif isinstance(value, str):
        comma = grid.decimal_comma and "," in value and "." not in value
        try:
            v = float(value.replace(",", ".") if comma else value)
        except ValueError:
            raise DataError(f"{grid.cell(k, c, column)}: not a number: {value!r}") from None
    else:  # a date, a time, TRUE/FALSE
        raise DataError(f"{grid.cell(k, c, column)}: not a number: {value!r}")
    if not np.isfinite(v):
        raise DataError(f"{grid.cell(k, c, column)}: non-finite value {value!r}")
    return v


def cell_text(grid: Grid, k: int, c: int, column: str) -> str:
    """A label cell (text or a number; 2.0 reads "2"); an empty cell is an error naming it."""
    row = grid.rows[k]
    value = row[c] if c < len(row) else None
    if _blank(value):
        raise DataError(f"{grid.cell(k, c, column)}: empty cell")
    return f"{value:g}" if isinstance(value, float) else str(value)


# -- from the map to SI readings ------------------------------------------------------------------------------
@dataclasses.dataclass
class Readings:
    """What a table holds, in SI: joint values, positions, rotations (or None), covariates."""

    q: np.ndarray
    p: np.ndarray
    R: np.ndarray | None
    covariates: dict
    joint_names: tuple
    joint_columns: tuple
    rows: np.ndarray  # row labels for messages (line numbers, or "row 17" in a workbook)
    units: dict  # column -> unit used
    position_unit: str | None  # the unit of x, y, z when they share one
    where: str  # the file (and sheet) for messages


def auto_map(header, path: str, joints=None) -> ColumnMap:
    """The column map of a header in the CSV layout (names less their unit suffix: `j1 [deg]`, `x [mm]`,
    `qw`..), with a `session` column when there is one."""
    names = {}
    for h in header:
        if isinstance(h, str) and h:
            name = split_unit(h)[0]
            if name in names:
                raise DataError(f"{path}: columns {names[name]!r} and {h!r} both name {name!r}")
            names[name] = h
    session = next((n for n in names if n.lower() == "session"), None)
    lay = cf.find_layout(list(names), path, joints, covariates=(session,) if session else ())
    form = {"rpy": ("euler", "xyz"), "rotvec": ("rotation_vector", None), "quaternion": ("quaternion_wxyz", None),
            "matrix": ("matrix", None), None: (None, None)}[lay.orientation]
    cov = {k: names[c] for k, c in lay.covariates.items() if c != session}
    return ColumnMap(tuple(names[j] for j in lay.joints), tuple(lay.joints), tuple(names[c] for c in lay.position),
                     form[0], form[1], tuple(names[c] for c in lay.orientation_columns), {},
                     names[session] if session else None, cov)


def column_unit(cmap: ColumnMap, column: str, default: str | None, where: str) -> str | None:
    """A column's unit: named in the map, else its header suffix, else `default`."""
    if column in cmap.units:
        unit_kind(cmap.units[column], f"{where}, column {column!r}")
        return cmap.units[column].strip().lower()
    suffix = split_unit(column)[1]
    if suffix is not None:
        unit_kind(suffix, f"{where}, column {column!r} (unit from the header; name another in the map's units)")
        return suffix.lower()
    return default


def joint_order(cmap: ColumnMap, joints, where: str) -> tuple[tuple, tuple]:
    """(names, columns) of the joints in the order of q: `joints` (e.g. the robot's) picked by name from a
    joints mapping, or given to a joints list by position; without `joints`, the map's order."""
    names = cmap.joint_names or tuple(split_unit(c)[0] for c in cmap.joints)
    if joints is None:
        return names, cmap.joints
    joints = tuple(joints)
    if cmap.joint_names is None:
        if len(joints) != len(cmap.joints):
            raise DataError(f"{where}: the column map lists {len(cmap.joints)} joint column(s) {list(cmap.joints)}, "
                            f"the robot has {len(joints)} joints {list(joints)}")
        return joints, cmap.joints
    missing = [j for j in joints if j not in names]
    extra = [n for n in names if n not in joints]
    if missing or extra:
        hint = suggestion(extra[0], joints) if extra else ""
        raise DataError(f"{where}: the column map's joints {list(names)} are not the robot's {list(joints)}: "
                        f"missing {missing}, unknown {extra}{hint}")
    col = dict(zip(names, cmap.joints))
    return joints, tuple(col[j] for j in joints)


def rotations(cmap: ColumnMap, block, rows, where: str) -> np.ndarray:
    """(N, 3, 3) rotations of the orientation columns (angles already in rad); errors name the row."""
    if cmap.form == "euler":
        big = np.abs(block).max(axis=1) > cf.MAX_ANGLE_RAD
        if big.any():
            i = int(np.flatnonzero(big)[0])
            raise DataError(f"{cf.at(where, rows[i])}: Euler angle of {np.abs(block[i]).max():.3g} rad: degrees given "
                            "as radians? name the unit in the column map's units or the header ('Rx [deg]')")
        return euler_matrices(block, cmap.sequence)
    if cmap.form == "quaternion_xyzw":
        return cf.rotations_from_columns("quaternion", block[:, [3, 0, 1, 2]], rows, where, 1.0)
    kind = {"quaternion_wxyz": "quaternion", "rotation_vector": "rotvec", "matrix": "matrix"}[cmap.form]
    return cf.rotations_from_columns(kind, block, rows, where, 1.0)


def readings(grid: Grid, cmap: ColumnMap, header_k: int, joints=None, length_unit=None, angle_unit=None,
             prismatic=()) -> Readings:
    """The rows below the header as SI readings; every unit checked for its quantity."""
    where = grid.path + (f", sheet {grid.sheet!r}" if grid.sheet is not None else "")
    header = grid.rows[header_k]
    check_header(header, cmap.columns(), where + (f", row {grid.numbers[header_k]}" if grid.sheet is not None
                                                  else f", line {grid.numbers[header_k]}"))
    names, joint_cols = joint_order(cmap, joints, where)
    length_default, angle_default = length_unit or "m", angle_unit or "rad"
    units = {}
    for name, c in zip(names, joint_cols):
        u = column_unit(cmap, c, length_default if name in prismatic else angle_default, where)
        if name in prismatic and unit_kind(u, where) != "length":
            raise DataError(f"{where}, column {c!r}: joint {name!r} is prismatic: its unit must be a length "
                            f"({', '.join(LENGTH_UNITS)}), got {u!r}")
        units[c] = u
    for c in cmap.position:
        units[c] = column_unit(cmap, c, length_default, where)
        unit_scale(units[c], "length", f"{where}, column {c!r}")
    angular = cmap.form in ("euler", "rotation_vector")
    for c in cmap.orientation:
        if angular:
            units[c] = column_unit(cmap, c, angle_default, where)
            unit_scale(units[c], "angle", f"{where}, column {c!r}")
        elif c in cmap.units:
            raise DataError(f"{where}, column {c!r}: {cmap.form} columns have no unit, the map gives {cmap.units[c]!r}")
    index = {h: i for i, h in enumerate(header)}
    body = range(header_k + 1, len(grid.rows))
    if not len(body):
        raise DataError(f"{where}: no data rows below the header")

    def block(cols):
        return np.array([[cell_number(grid, k, index[c], c) for c in cols] for k in body]).reshape(len(body), len(cols))

    def scales(cols):
        return np.array([(LENGTH_UNITS | ANGLE_UNITS)[units[c]] for c in cols])

    rows = np.array([grid.row_label(k) for k in body])
    q = block(joint_cols) * scales(joint_cols)
    p = block(cmap.position) * scales(cmap.position)
    R = None
    if cmap.form is not None:
        ob = block(cmap.orientation)
        R = rotations(cmap, ob * scales(cmap.orientation) if angular else ob, rows, where)
    cov = {name: block([c])[:, 0] for name, c in cmap.covariates.items()}
    if cmap.session:
        cov["session"] = np.array([cell_text(grid, k, index[cmap.session], cmap.session) for k in body], dtype=str)
    shared = {units[c] for c in cmap.position}
    return Readings(q, p, R, cov, tuple(names), tuple(joint_cols), rows, units, shared.pop() if len(shared) == 1 else None, where)


def check_readings(r: Readings, limits=None) -> None:
    """Values that look like another unit than the stated one (`csvfile.check_*_units`), per column unit."""
    for unit in ("rad", "deg"):
        cols = [j for j, c in enumerate(r.joint_columns) if r.units[c] == unit]
        raw = r.q[:, cols] / ANGLE_UNITS[unit]
        cf.check_joint_units(raw, [r.joint_columns[j] for j in cols], r.rows, unit, r.where)
    metres = [j for j, c in enumerate(r.joint_columns) if r.units[c] == "m"]
    cf.check_prismatic_units(r.q[:, metres], [r.joint_columns[j] for j in metres], r.rows, "m", r.where,
                             [r.joint_columns[j] for j in metres])
    prismatic = [c for c in r.joint_columns if r.units[c] in LENGTH_UNITS]
    by_column = {c: (limits or {})[n] for n, c in zip(r.joint_names, r.joint_columns) if n in (limits or {})}
    cf.check_limit_units(r.q, list(r.joint_columns), r.rows, r.where, by_column, prismatic)
    if r.position_unit in ("m", "mm"):
        cf.check_length_units(r.p, r.rows, r.position_unit, r.where)


def read(path, columns=None, joints=None, length_unit=None, angle_unit=None, sheet=None, header_row=None,
         prismatic=()) -> Readings:
    """SI readings of a workbook or text export through a column map (a mapping, a YAML path, or None for the
    CSV layout); `sheet` and `header_row` override the map's."""
    path = os.fspath(path)
    for kind, unit, allowed in (("length_unit", length_unit, LENGTH_UNITS), ("angle_unit", angle_unit, ANGLE_UNITS)):
        if unit is not None and unit not in allowed:
            raise DataError(f"{path}: {kind} must be one of {', '.join(allowed)}, got {unit!r}")
    cmap = None if columns is None else load_map(columns)
    grid = read_grid(path, sheet or (cmap.sheet if cmap else None), cmap.delimiter if cmap else None)
    if not grid.rows:
        raise DataError(f"{path}: empty" + (f" sheet {grid.sheet!r}" if grid.sheet is not None else " file"))
    k = header_index(grid, cmap.columns() if cmap else (), header_row or (cmap.header_row if cmap else None))
    if cmap is None:
        cmap = auto_map(grid.rows[k], path, joints)
        joints = None  # auto_map has put them in order
    return readings(grid, cmap, k, joints, length_unit, angle_unit, tuple(prismatic))


__all__ = ["ANGLE_UNITS", "ColumnMap", "FORMS", "Grid", "LENGTH_UNITS", "Readings", "auto_map", "check_readings",
           "euler_matrices", "load_map", "parse_map", "read", "read_grid", "split_unit"]
