"""Datasets: joint readings, device readings and covariates, from arrays or CSV."""

from __future__ import annotations

import numpy as np

from jaxcal.fit.csvfile import DataError, DataWarning, UnitWarning  # noqa: F401  (re-exported)
from jaxcal.measure import Device, as_device, device_class, make_device


def _canonical_readings(device: Device, y, R, p, n: int):
    """Readings as an array of shape (N, *device.reading_shape)."""
    y = device.readings(y, R, p)
    if y.shape != (n,) + device.reading_shape:
        raise DataError(f"{device.kind} readings must have shape (N={n}, {', '.join(map(str, device.reading_shape))}), got {y.shape}")
    return y


def _check_finite(arr, what):
    bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1)
    if bad.any():
        raise DataError(f"{what}: non-finite values in sample(s) {np.flatnonzero(bad)[:10].tolist()}")



def _read_layout(path, delimiter, lay, readings, length_unit, angle_unit, prismatic):
    """The rows of a CSV laid out as `lay` (joints, the reading columns, covariates): (table, length unit, angle
    unit, prismatic joints, column index by name, joint values as in the file, joint values in m / rad)."""
    from jaxcal.fit import csvfile as cf

    tab = cf.read_table(path, delimiter, needed=lay.joints + list(readings) + list(lay.covariates.values()))
    length = cf.resolve_unit("length", length_unit, tab.units.get("length"), path)
    angle = cf.resolve_unit("angle", angle_unit, tab.units.get("angle"), path)
    prismatic = tuple(prismatic) + tuple(tab.units.get("prismatic", ()))
    col = {h: i for i, h in enumerate(tab.header)}
    q_raw = tab.values[:, [col[c] for c in lay.joints]]
    return tab, length, angle, prismatic, col, q_raw, q_raw * cf.joint_scale(lay.joints, prismatic, length, angle)


def _covariates(tab, lay, col) -> dict:
    """The covariate columns of a CSV laid out as `lay` (numbers), and its session labels (text) when it has them."""
    cov = {name: tab.values[:, col[c]] for name, c in lay.covariates.items()}
    if lay.session is not None:
        cov["session"] = tab.column_text(lay.session)
    return cov

class Dataset:
    """Joint values q (N, n_inputs), device readings y and optional covariates.

    `Dataset(q=Q, y=Y, device="position")`; for "pose" give y (N, 4, 4) or R= (N, 3, 3) and
    p= (N, 3); for "multi_position" y (N, K, 3), K marker points per sample.
    Covariates (e.g. "time", "temperature", "direction") are arrays of length N.
    """

    def __init__(self, q, y=None, device="position", covariates=None, R=None, p=None, joint_names=None, source=None):
        self.device = as_device(device, y)
        q = np.array(q, float)  # a copy: editing data.q (a glitch, a unit fix) leaves the caller's array as it was
        if q.ndim == 1:
            q = q[:, None]
        if q.ndim != 2:
            raise DataError(f"q must be (N, n_inputs), got shape {q.shape}")
        self.q = q
        self.y = _canonical_readings(self.device, y, R, p, len(q))
        _check_finite(self.q, "q")
        _check_finite(self.y, "y")
        self.covariates = {}
        for k, v in (covariates or {}).items():
            v = np.asarray(v)
            if len(v) != len(q):
                raise DataError(f"covariate {k!r} has {len(v)} values for {len(q)} samples")
            self.covariates[k] = v
        self.joint_names = tuple(joint_names) if joint_names is not None else None
        self.source = source
        self.units = {"length": "m", "angle": "rad"}  # the units the values were given in (SI inside)

    def __len__(self):
        return len(self.q)

    def __repr__(self):
        cov = f", covariates={sorted(self.covariates)}" if self.covariates else ""
        return f"Dataset(N={len(self)}, n_inputs={self.q.shape[1]}, device={self.device.kind!r}{cov})"

    def subset(self, idx) -> "Dataset":
        idx = np.asarray(idx)
        out = Dataset(self.q[idx], self.y[idx], self.device, {k: v[idx] for k, v in self.covariates.items()},
                      joint_names=self.joint_names, source=self.source)
        out.units = dict(self.units)
        return out

    def split(self, fraction=0.8, seed=0):
        """(train, held-out) random split."""
        perm = np.random.default_rng(seed).permutation(len(self))
        k = int(round(fraction * len(self)))
        return self.subset(np.sort(perm[:k])), self.subset(np.sort(perm[k:]))

    @classmethod
    def from_csv(cls, path, joints=None, device=None, position_columns=None, length_unit=None, angle_unit=None,
                 covariates=(), delimiter=",", marker=None, check_units=True, prismatic=(), limits=None):
        """Read a measurement CSV (layout in `jaxcal.fit.csvfile` and docs/file-formats.md).

        joints: the joint columns in the order of q (default: every column that is not a
        measurement or a covariate, in file order; pass `robot.joint_names` to check them).
        device: "position" or "pose" (default: "pose" when the marker has orientation columns).
        marker: which marker's columns to read when there are several (`x1..`, `x2..`; default the first);
        with device "multi_position" (or "markers"), the markers read together (default all of them), e.g. (1, 2, 3).
        length_unit ("m"/"mm"), angle_unit ("rad"/"deg"): override the file's `# units:` line; default SI.
        prismatic: joint columns that are lengths (in the length unit), added to those of a `# prismatic:`
        header line; `csvfile.prismatic_joints(robot)` lists a robot's.
        check_units: raise (or warn) on values that look like another unit (see `csvfile.check_*_units`).
        limits: {joint: (lower, upper)} in SI (`csvfile.joint_limits(robot)`); a column far beyond them that fits them
        in the other unit (57.3x for degrees read as radians, 1000x for millimetres) is an error.
        Errors name the file, the 1-based line and the column.
        """
        from jaxcal.fit import csvfile as cf

        path = str(path)
        if length_unit is not None and length_unit not in cf.LENGTH_SCALE:
            raise DataError(f"{path}: length_unit must be 'm' or 'mm', got {length_unit!r}")
        if angle_unit is not None and angle_unit not in cf.ANGLE_SCALE:
            raise DataError(f"{path}: angle_unit must be 'rad' or 'deg', got {angle_unit!r}")
        head = cf.read_table(path, delimiter, header_only=True)  # the columns first, then the rows
        dev_class = None if device is None else type(device) if isinstance(device, Device) else device_class(device)
        reading = None if dev_class is None else dev_class.marker_reading
        if dev_class is not None and dev_class.kind in cf.INSTRUMENT_COLUMNS:
            return cls._instrument_csv(path, head.header, device or dev_class.kind, joints, length_unit, angle_unit,
                                       covariates, delimiter, check_units, prismatic, limits)
        if reading == "points":
            return cls._multi_marker_csv(path, head.header, device, joints, marker, length_unit, angle_unit, covariates,
                                         delimiter, check_units, prismatic, limits)
        lay = cf.find_layout(head.header, path, joints, position_columns, marker, covariates, orientation=reading != "point")
        if reading == "frame" and lay.orientation is None:
            raise DataError(f"{path}: device {dev_class.kind!r} needs orientation columns "
                            "(phix, phiy, phiz / rvx, rvy, rvz / qw, qx, qy, qz / r11..r33)")
        if dev_class is not None and reading not in ("point", "frame"):
            raise DataError(f"{path}: CSV readings are positions or poses, not {dev_class.kind!r}")
        cols = lay.joints + lay.position + lay.orientation_columns + list(lay.covariates.values())
        tab = cf.read_table(path, delimiter, needed=cols)
        length = cf.resolve_unit("length", length_unit, tab.units.get("length"), path)
        angle = cf.resolve_unit("angle", angle_unit, tab.units.get("angle"), path)
        prismatic = tuple(prismatic) + tuple(tab.units.get("prismatic", ()))
        col = {h: i for i, h in enumerate(tab.header)}
        block = lambda names: tab.values[:, [col[c] for c in names]]  # noqa: E731
        q_raw, p = block(lay.joints), block(lay.position) * cf.LENGTH_SCALE[length]
        q = q_raw * cf.joint_scale(lay.joints, prismatic, length, angle)
        if check_units:
            cf.check_joint_units(q_raw, lay.joints, tab.lines, angle, path, prismatic)
            cf.check_prismatic_units(q_raw, lay.joints, tab.lines, length, path, prismatic)
            cf.check_limit_units(q, lay.joints, tab.lines, path, limits or {}, prismatic)
            cf.check_length_units(p, tab.lines, length, path)
        cov = {name: tab.values[:, col[c]] for name, c in lay.covariates.items()}
        if lay.session is not None:
            cov["session"] = tab.column_text(lay.session)
        if lay.orientation is not None:
            R = cf.rotations_from_columns(lay.orientation, block(lay.orientation_columns), tab.lines, path, cf.ANGLE_SCALE[angle])
            ds = cls(q=q, R=R, p=p, device=device or "pose", covariates=cov, joint_names=lay.joints, source=path)
        else:
            ds = cls(q=q, y=p, device=device or "position", covariates=cov, joint_names=lay.joints, source=path)
        ds.units = {"length": length, "angle": angle}
        return ds

    @classmethod
    def from_table(cls, path, columns=None, device=None, joints=None, length_unit=None, angle_unit=None, sheet=None,
                   header_row=None, check_units=True, prismatic=(), limits=None):
        """Read an .xlsx workbook or a delimited text export (tracker, mocap) through a column map
        (`jaxcal.fit.tables`, docs/file-formats.md).

        columns: the column map, a mapping or the path of a YAML file holding one; None reads the CSV layout
        (column names less a unit suffix such as `x [mm]`).
        device: "position" or "pose" (default: "pose" when the map has orientation columns).
        joints: the joint names in the order of q (`robot.joint_names`): picked by name from a joints mapping,
        given by position to a joints list.
        length_unit, angle_unit: the unit of columns whose unit neither the map nor the header names (default SI).
        sheet, header_row: override the map's (default the first sheet, a detected header row).
        prismatic: joints whose columns are lengths; limits, check_units: as `from_csv`.
        A `session` column becomes `covariates["session"]` (strings); other covariates are numbers.
        Errors name the file, the sheet and cell (`B17`) or the line, and the column.
        """
        from jaxcal.fit import tables

        r = tables.read(path, columns, joints, length_unit, angle_unit, sheet, header_row, prismatic)
        if check_units:
            tables.check_readings(r, limits)
        dev_class = None if device is None else type(device) if isinstance(device, Device) else device_class(device)
        reading = None if dev_class is None else dev_class.marker_reading
        if reading == "frame" and r.R is None:
            raise DataError(f"{r.where}: device {dev_class.kind!r} needs orientation columns (the column map's 'orientation')")
        if dev_class is not None and reading not in ("point", "frame"):
            raise DataError(f"{r.where}: table readings are positions or poses, not {dev_class.kind!r}")
        if r.R is not None and reading != "point":
            ds = cls(q=r.q, R=r.R, p=r.p, device=device or "pose", covariates=r.covariates, joint_names=r.joint_names,
                     source=str(path))
        else:
            ds = cls(q=r.q, y=r.p, device=device or "position", covariates=r.covariates, joint_names=r.joint_names,
                     source=str(path))
        angles = [u for u in r.units.values() if u in tables.ANGLE_UNITS]
        ds.units = {"length": r.position_unit, "angle": angles[0] if angles else angle_unit or "rad", "columns": dict(r.units)}
        return ds

    @classmethod
    def _instrument_csv(cls, path, header, device, joints, length_unit, angle_unit, covariates, delimiter, check_units,
                        prismatic, limits=None):
        """`from_csv` for an instrument whose readings are sight angles and/or a range (`csvfile.INSTRUMENT_COLUMNS`:
        `azimuth, elevation` in the angle unit, `range` in the length unit)."""
        from jaxcal.fit import csvfile as cf

        dev = as_device(device)
        columns = cf.INSTRUMENT_COLUMNS[dev.kind]
        names = [c for c, _ in columns]
        lay = cf.find_layout(header, path, joints, names, None, covariates, orientation=False)
        tab, length, angle, prismatic, col, q_raw, q = _read_layout(path, delimiter, lay, names, length_unit, angle_unit,
                                                                    prismatic)
        scale = np.array([cf.ANGLE_SCALE[angle] if kind == "angle" else cf.LENGTH_SCALE[length] for _, kind in columns])
        y = tab.values[:, [col[c] for c in names]] * scale
        if check_units:
            cf.check_joint_units(q_raw, lay.joints, tab.lines, angle, path, prismatic)
            cf.check_prismatic_units(q_raw, lay.joints, tab.lines, length, path, prismatic)
            cf.check_limit_units(q, lay.joints, tab.lines, path, limits or {}, prismatic)
            for k, (name, kind) in enumerate(columns):
                big = np.abs(y[:, k]) > (cf.MAX_ANGLE_RAD if kind == "angle" else cf.MAX_POSITION_M)
                if big.any():
                    i = int(np.flatnonzero(big)[0])
                    what = "degrees given as radians" if kind == "angle" else "millimetres given as metres"
                    raise DataError(f"{cf.at(path, tab.lines[i])}, column {name!r}: {tab.values[i, col[name]]:.6g} is too "
                                    f"large for {angle if kind == 'angle' else length}: {what}? state the unit")
        cov = _covariates(tab, lay, col)
        ds = cls(q=q, y=y, device=dev, covariates=cov, joint_names=lay.joints, source=path)
        ds.units = {"length": length, "angle": angle}
        return ds

    @classmethod
    def _multi_marker_csv(cls, path, header, device, joints, markers, length_unit, angle_unit, covariates, delimiter,
                          check_units, prismatic, limits=None):
        """`from_csv` for a multi-marker position device: the columns x_k, y_k, z_k of each marker k in `markers`
        (default every marker with all three columns), readings (N, K, 3)."""
        from jaxcal.fit import csvfile as cf

        found = cf.find_layout(header, path, joints, None, None, covariates, orientation=False).markers
        markers = found if markers is None else [str(m) for m in np.atleast_1d(markers)]
        missing = [m for m in markers if m not in found]
        if missing or not markers:
            raise DataError(f"{path}: marker(s) {missing or markers} not found; markers with x, y, z columns: "
                            f"{[m or '(unnumbered)' for m in found]}")
        position = [f"{a}{m}" for m in markers for a in "xyz"]
        lay = cf.find_layout(header, path, joints, position, None, covariates, orientation=False)
        tab, length, angle, prismatic, col, q_raw, q = _read_layout(path, delimiter, lay, position, length_unit, angle_unit,
                                                                    prismatic)
        p = tab.values[:, [col[c] for c in position]].reshape(len(q_raw), len(markers), 3) * cf.LENGTH_SCALE[length]
        if check_units:
            cf.check_joint_units(q_raw, lay.joints, tab.lines, angle, path, prismatic)
            cf.check_prismatic_units(q_raw, lay.joints, tab.lines, length, path, prismatic)
            cf.check_limit_units(q, lay.joints, tab.lines, path, limits or {}, prismatic)
            for k in range(len(markers)):
                cf.check_length_units(p[:, k], tab.lines, length, path)
        dev = device if isinstance(device, Device) else make_device("multi_position", points=len(markers))
        if dev.reading_shape != (len(markers), 3):
            raise DataError(f"{path}: device has {dev.reading_shape[0]} marker points, the file gives markers {markers}")
        cov = _covariates(tab, lay, col)
        ds = cls(q=q, y=p, device=dev, covariates=cov, joint_names=lay.joints, source=path)
        ds.units = {"length": length, "angle": angle}
        return ds

    def to_csv(self, path, length_unit="m", angle_unit="rad", joints=None, prismatic=()):
        """Write this dataset as CSV (joint columns, x, y, z, and roll-pitch-yaw phix, phiy, phiz for
        poses, or x1, y1, z1, x2, ... for the markers of a multi_position device, then the covariates) with a
        `# units:` header line; atomically (temp file, then rename). Prismatic
        joints (names in `prismatic`) are written in the length unit and listed in a `# prismatic:` line."""
        from scipy.spatial.transform import Rotation

        from jaxcal.fit import csvfile as cf
        from jaxcal.io_atomic import write_text_atomic

        reading = self.device.marker_reading
        instrument = cf.INSTRUMENT_COLUMNS.get(self.device.kind)
        if reading not in ("point", "points", "frame") and instrument is None:
            raise DataError(f"to_csv writes position, multi-marker, pose or {'/'.join(cf.INSTRUMENT_COLUMNS)} data, "
                            f"not {self.device.kind!r}")
        joints = list(joints or self.joint_names or [f"q{i + 1}" for i in range(self.q.shape[1])])
        ls, an = 1.0 / cf.LENGTH_SCALE[length_unit], 1.0 / cf.ANGLE_SCALE[angle_unit]
        if instrument is not None:
            meas = self.y * np.array([an if kind == "angle" else ls for _, kind in instrument])
            names = [c for c, _ in instrument]
        elif reading == "point":
            meas, names = self.y * ls, ["x", "y", "z"]
        elif reading == "points":  # marker k in columns xk, yk, zk
            meas = self.y.reshape(len(self.y), -1) * ls
            names = [f"{a}{k}" for k in range(1, self.y.shape[1] + 1) for a in "xyz"]
        else:
            rpy = Rotation.from_matrix(self.y[:, :3, :3]).as_euler("xyz") * an
            meas, names = np.hstack([self.y[:, :3, 3] * ls, rpy]), ["x", "y", "z", "phix", "phiy", "phiz"]
        cov = sorted(c for c in self.covariates if c != cf.SESSION_COLUMN)
        q_file = self.q / cf.joint_scale(joints, prismatic, length_unit, angle_unit)
        table = np.hstack([q_file, meas] + [np.asarray(self.covariates[c], float)[:, None] for c in cov])
        rows = [[f"{v:.17g}" for v in row] for row in table]
        if cf.SESSION_COLUMN in self.covariates:  # text labels, last
            cov.append(cf.SESSION_COLUMN)
            rows = [row + [str(label)] for row, label in zip(rows, self.covariates[cf.SESSION_COLUMN])]
        lines = [f"# units: length={length_unit}, angle={angle_unit}"]
        lines += [f"# prismatic: {', '.join(j for j in joints if j in prismatic)}"] if set(prismatic) & set(joints) else []
        lines += [",".join(joints + names + cov)]
        lines += [",".join(row) for row in rows]
        return write_text_atomic(str(path), "\n".join(lines) + "\n")
