"""Spreadsheets and vendor exports read through a column map (jaxcal.fit.tables, Dataset.from_table):
units per column, Euler conventions, header detection, sessions, formulas, and errors naming the cell."""

import io
import itertools
import re
import zipfile

import numpy as np
import openpyxl
import pytest
import yaml
from scipy.spatial.transform import Rotation

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.fit.tables import euler_matrices
from jaxcal.io_atomic import atomic_path, write_text_atomic

JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")  # the Stanford arm's; j3 is prismatic
EULER = ["".join(p) for p in itertools.permutations("xyz")] + [a + b + a for a in "xyz" for b in "xyz" if a != b]


@pytest.fixture(scope="module")
def truth():
    """Stanford-arm pose readings in SI, eight samples."""
    rb = jc.robots.get("stanford")
    q = jc.random_configurations(rb, 8, seed=4)
    data = jc.simulate(rb, jc.perturb(rb, 0.002, seed=5), q, "pose")
    return np.asarray(data.q), np.asarray(data.y)


def _elementary(axis, t):
    """Rotation about a coordinate axis, written out by hand (independent of jaxcal)."""
    c, s = np.cos(t), np.sin(t)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


@pytest.mark.parametrize("seq", EULER + [s.upper() for s in EULER])
def test_euler_sequences_match_products_and_scipy(seq):
    angles = np.random.default_rng(len(seq) + ord(seq[0]) + ord(seq[1])).uniform(-3, 3, (5, 3))
    got = euler_matrices(angles, seq)
    factors = [[_elementary(a, t) for a, t in zip(seq.lower(), row)] for row in angles]
    by_hand = np.stack([f[0] @ f[1] @ f[2] if seq.isupper() else f[2] @ f[1] @ f[0] for f in factors])
    np.testing.assert_allclose(got, by_hand, atol=1e-12)
    np.testing.assert_allclose(got, Rotation.from_euler(seq, angles).as_matrix(), atol=1e-12)  # upper: intrinsic


def _save_workbook(wb, path, cached=None):
    """Save through an atomic write; `cached` {cell: value} stores a result for formula cells, as a spreadsheet
    program does (openpyxl writes formulas without one)."""
    buf = io.BytesIO()
    wb.save(buf)
    with atomic_path(str(path)) as tmp, zipfile.ZipFile(io.BytesIO(buf.getvalue())) as src, \
            zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename.startswith("xl/worksheets/") and cached:
                text = data.decode()
                for cell, value in cached.items():
                    text = re.sub(rf'(<c r="{cell}"[^>]*><f>[^<]*</f>)<v\s*/?>(</v>)?', rf"\g<1><v>{value}</v>", text)
                data = text.encode()
            dst.writestr(item, data)
    return path


def _orientation_block(R, form):
    if form == "quaternion_xyzw":
        return ["QX", "QY", "QZ", "QW"], Rotation.from_matrix(R).as_quat(), {}
    return ["Rz [deg]", "Ry [deg]", "Rx [deg]"], np.degrees(Rotation.from_matrix(R).as_euler("ZYX")), {"sequence": "ZYX"}


def _tracker_workbook(tmp_path, truth, form):
    """A tracker export as a user brings it: a preamble, the header on row 4, joints in deg (j3 in mm), positions
    in mm, an orientation, a session column, a temperature with a formula cell, and a blank row."""
    q, y = truth
    ocols, oblock, extra = _orientation_block(y[:, :3, :3], form)
    jcols = [f"A{k + 1} [{'mm' if k == 2 else 'deg'}]" for k in range(6)]
    qfile = np.degrees(q)
    qfile[:, 2] = q[:, 2] * 1e3
    wb = openpyxl.Workbook()
    ws = wb.active
    ws.title = "Notes"
    ws["A1"] = "not the data"
    data = wb.create_sheet("Data")
    data.append(["Leica AT960 export"])
    data.append(["Operator", "J. Doe"])
    data.append([])
    data.append(["Session", *jcols, "X [mm]", "Y [mm]", "Z [mm]", "T [C]", *ocols])
    for i in range(len(q)):
        if i == 3:
            data.append([])  # a blank row between the samples
        session = "morning" if i < 4 else 2
        data.append([session, *qfile[i], *(y[i, :3, 3] * 1e3), 20.0 + i, *oblock[i]])
    data["K5"] = "=20+1"  # the first sample's temperature, a formula
    path = _save_workbook(wb, tmp_path / "tracker.xlsx", cached={"K5": 21})
    cmap = {"sheet": "Data", "session": "Session", "joints": {f"j{k + 1}": c for k, c in enumerate(jcols)},
            "position": {"x": "X [mm]", "y": "Y [mm]", "z": "Z [mm]"},
            "orientation": {"form": form, "columns": ocols, **extra}, "covariates": {"temperature": "T [C]"}}
    return path, cmap


@pytest.mark.parametrize("form", ["quaternion_xyzw", "euler"])
def test_xlsx_tracker_export_reads_to_the_truth(tmp_path, truth, form):
    q, y = truth
    path, cmap = _tracker_workbook(tmp_path, truth, form)
    before = path.read_bytes()
    map_file = write_text_atomic(str(tmp_path / "map.yaml"), yaml.safe_dump(cmap))
    for columns in (cmap, map_file):
        d = jc.Dataset.from_table(path, columns=columns, joints=JOINTS, prismatic=("j3",))
        assert d.device.kind == "pose" and d.joint_names == JOINTS and len(d) == len(q)
        np.testing.assert_allclose(d.q, q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(d.y, y, rtol=0, atol=1e-12)
        assert d.covariates["session"].dtype.kind == "U"
        assert list(d.covariates["session"]) == ["morning"] * 4 + ["2"] * 4
        np.testing.assert_array_equal(d.covariates["temperature"], [21.0, *(20.0 + np.arange(1, 8))])
        assert d.units["columns"]["A3 [mm]"] == "mm" and d.units["length"] == "mm"
    assert path.read_bytes() == before  # the input is never written
    position = jc.Dataset.from_table(path, columns=cmap, device="position")
    np.testing.assert_allclose(position.y, y[:, :3, 3], rtol=0, atol=1e-12)


def test_xlsx_without_a_map_reads_the_csv_layout(tmp_path, truth):
    q, y = truth
    wb = openpyxl.Workbook()
    ws = wb.active
    ws.append(["exported 2026-11-26"])
    ws.append([*(f"j{k + 1} [deg]" for k in range(6)), "x [mm]", "y [mm]", "z [mm]", "session"])
    for i in range(len(q)):
        ws.append([*np.degrees(q[i]), *(y[i, :3, 3] * 1e3), "A"])
    path = _save_workbook(wb, tmp_path / "plain.xlsx")
    d = jc.Dataset.from_table(path, check_units=False)  # j3 given in deg here, so no unit checks
    assert d.joint_names == JOINTS and d.device.kind == "position"
    np.testing.assert_allclose(d.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.y, y[:, :3, 3], rtol=0, atol=1e-12)
    assert list(d.covariates["session"]) == ["A"] * len(q)


def test_semicolon_decimal_comma_text_export(tmp_path, truth):
    """A European tracker export: preamble lines, ';' between fields, decimal commas, extrinsic xyz Euler angles."""
    q, y = truth
    rpy = np.degrees(Rotation.from_matrix(y[:, :3, :3]).as_euler("xyz"))
    lines = ["Leica Geosystems;AT960", "Datum;26.11.2026", "Einheiten;mm;Grad", "",
             "Punkt;Achse 1;Achse 2;Achse 3;Achse 4;Achse 5;Achse 6;X;Y;Z;RX;RY;RZ;Messung"]
    for i in range(len(q)):
        vals = [*np.degrees(q[i, :2]), q[i, 2] * 1e3, *np.degrees(q[i, 3:]), *(y[i, :3, 3] * 1e3), *rpy[i]]
        lines.append(";".join([f"P{i + 1}", *(f"{v:.17g}".replace(".", ",") for v in vals), str(i // 4 + 1)]))
    path = write_text_atomic(str(tmp_path / "export.txt"), "\r\n".join(lines) + "\r\n")
    cmap = {"joints": [f"Achse {k}" for k in range(1, 7)], "position": ["X", "Y", "Z"],
            "orientation": {"form": "euler", "sequence": "xyz", "columns": ["RX", "RY", "RZ"]}, "session": "Messung",
            "units": {**{f"Achse {k}": "deg" for k in range(1, 7)}, "Achse 3": "mm", "X": "mm", "Y": "mm", "Z": "mm",
                      "RX": "deg", "RY": "deg", "RZ": "deg"}}
    d = jc.Dataset.from_table(path, columns=cmap, joints=JOINTS, prismatic=("j3",))
    assert d.joint_names == JOINTS
    np.testing.assert_allclose(d.q, q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.y, y, rtol=0, atol=1e-12)
    assert list(d.covariates["session"]) == ["1"] * 4 + ["2"] * 4
    lines[6] = lines[6].replace(lines[6].split(";")[8], "-")  # Y of the second sample
    write_text_atomic(path, "\n".join(lines) + "\n")
    with pytest.raises(jc.DataError, match=r"export.txt, line 7, column 'Y': not a number: '-'"):
        jc.Dataset.from_table(path, columns=cmap)


def test_tab_separated_mocap_export_with_rotation_vectors(tmp_path, truth):
    q, y = truth
    rv = Rotation.from_matrix(y[:, :3, :3]).as_rotvec()
    lines = ["Qualisys export", "Frames\t8", "q1 (rad)\tq2 (rad)\tq3 (m)\tq4 (rad)\tq5 (rad)\tq6 (rad)\tPX (cm)\tPY (cm)\tPZ (cm)"
             "\tRV1\tRV2\tRV3"]
    lines += ["\t".join(f"{v:.17g}" for v in (*q[i], *(y[i, :3, 3] * 100), *rv[i])) for i in range(len(q))]
    path = write_text_atomic(str(tmp_path / "mocap.tsv"), "\n".join(lines) + "\n")
    cmap = {"joints": {j: f"q{k + 1} ({'m' if k == 2 else 'rad'})" for k, j in enumerate(JOINTS)},
            "position": ["PX (cm)", "PY (cm)", "PZ (cm)"],
            "orientation": {"form": "rotation_vector", "columns": ["RV1", "RV2", "RV3"]}}
    d = jc.Dataset.from_table(path, columns=cmap, joints=JOINTS[::-1])  # q in the order asked for
    np.testing.assert_allclose(d.q, q[:, ::-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(d.y, y, rtol=0, atol=1e-12)


@pytest.mark.parametrize("edit, message", [
    (lambda m: m["position"].update(z="Z [m]"),
     r"tracker.xlsx, sheet 'Data', row 4: unknown column\(s\) \['Z \[m\]'\] named in the column map \(did you mean 'Z \[mm\]'"),
    (lambda m: m.update(units={"X [mm]": "furlong"}), r"column 'X \[mm\]': unknown unit 'furlong'; expected one of m, mm, cm, in"),
    (lambda m: m.update(units={"X [mm]": "deg"}), r"column 'X \[mm\]': unit 'deg' is not a length"),
    (lambda m: m["orientation"].update(columns=["QX", "QY", "QZ"]),
     r"orientation form 'quaternion_xyzw' takes 4 columns, got 3"),
    (lambda m: m["orientation"].update(form="euler", sequence="ZZX", columns=["QX", "QY", "QZ"]),
     r"Euler sequence must be three axes .* got 'ZZX'"),
    (lambda m: m.update(sheet="Daten"), r"no sheet 'Daten' \(did you mean 'Data'\?\)"),
    (lambda m: m.update(postion={}), r"unknown key 'postion' \(did you mean 'position'\?\)"),
])
def test_bad_maps_name_the_problem(tmp_path, truth, edit, message):
    path, cmap = _tracker_workbook(tmp_path, truth, "quaternion_xyzw")
    edit(cmap)
    with pytest.raises(jc.DataError, match=message):
        jc.Dataset.from_table(path, columns=cmap)


def test_bad_cells_are_named(tmp_path, truth):
    path, cmap = _tracker_workbook(tmp_path, truth, "quaternion_xyzw")
    wb = openpyxl.load_workbook(path)
    wb["Data"]["I9"] = "n/a"  # Y of the fourth sample (row 9: the blank row 8 comes before it)
    _save_workbook(wb, path, cached={"K5": 21})
    with pytest.raises(jc.DataError, match=r"tracker.xlsx, sheet 'Data', cell I9, column 'Y \[mm\]': not a number: 'n/a'"):
        jc.Dataset.from_table(path, columns=cmap)
    wb["Data"]["I9"] = 1.0
    _save_workbook(wb, path)  # the formula keeps no result
    with pytest.raises(jc.DataError, match=r"cell K5, column 'T \[C\]': formula '=20\+1' has no saved value"):
        jc.Dataset.from_table(path, columns=cmap)


def test_unit_mistake_in_a_map_is_caught(tmp_path, truth):
    path, cmap = _tracker_workbook(tmp_path, truth, "quaternion_xyzw")
    cmap["units"] = {c: "rad" for c in cmap["joints"].values() if "deg" in c}  # degrees declared as radians
    with pytest.raises(jc.DataError, match=r"sheet 'Data', row \d+, column 'A\d \[deg\]'.*degrees given as radians"):
        jc.Dataset.from_table(path, columns=cmap)


def test_cli_loads_xlsx_through_the_map(tmp_path, truth):
    from jaxcal.cli import load_job_data

    path, cmap = _tracker_workbook(tmp_path, truth, "quaternion_xyzw")
    map_file = write_text_atomic(str(tmp_path / "map.yaml"), yaml.safe_dump(cmap))
    data, found = load_job_data({"data": str(path), "columns": map_file}, jc.robots.get("stanford"))
    assert data.device.kind == "pose" and data.joint_names == JOINTS and found == []
    np.testing.assert_allclose(data.y, truth[1], rtol=0, atol=1e-12)


def test_calibrate_reads_xlsx_with_a_column_map(tmp_path, truth, capsys):
    """`jaxcal calibrate ROBOT DATA.xlsx --columns MAP.yaml`: bad map entries are one error line, exit 2."""
    path, cmap = _tracker_workbook(tmp_path, truth, "quaternion_xyzw")
    cmap["joints"]["j7"] = cmap["joints"].pop("j6")
    map_file = write_text_atomic(str(tmp_path / "map.yaml"), yaml.safe_dump(cmap))
    rc = main(["calibrate", "stanford", str(path), "--columns", map_file, "--out", str(tmp_path / "out"), "-q"])
    err = " ".join(capsys.readouterr().err.split())
    assert rc == 2 and "joints ['j1', 'j2', 'j3', 'j4', 'j5', 'j7'] are not the robot's" in err
    assert not (tmp_path / "out").exists()
