"""Calibration job configuration: a YAML or TOML file whose keys mirror `jaxcal calibrate`'s options.

    robot: arm.urdf            # built-in name, robot YAML or URDF (paths relative to this file)
    base: base_link            # URDF chain, first link
    tip: tool0                 # URDF chain, last link
    data: measurements.csv
    out: calib-output
    device: position           # position | pose (default: from the CSV columns)
    marker: 1                  # which marker's x, y, z when the CSV has several
    units: {length: mm, angle: deg}
    holdout: 0.25              # fraction of the samples kept out of the fit
    seed: 0
    solver: lm
    free: [j2.x, j2.y]         # robot parameters to estimate (default: all free ones, base set)
    known: [dev]               # device parameters taken as known
    sigma_position: 1.0e-4     # m, residual weight 1/sigma
    sigma_orientation: 1.0e-3  # rad
    max_steps: 200
    rtol: 1.0e-8               # solver tolerances (default: the calibration core's)
    atol: 1.0e-10

Errors name the file and the key: unknown keys (with the closest known key), keys given twice (YAML;
TOML refuses them itself), names given twice in `joints`, `free` or `known`, wrong values.
"""

from __future__ import annotations

import os
import tomllib

import yaml

from jaxcal.fit.core import SOLVERS
from jaxcal.names import duplicates, suggestion
from jaxcal.yamlfile import load_yaml


class ConfigError(ValueError):
    """A job file that cannot be used; the message names the file and the key."""


def _string(v):
    return isinstance(v, str) and v != ""


def _number(v):
    """A finite int or float (not a bool, NaN or inf)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v and abs(v) != float("inf")


def _string_list(v):
    return isinstance(v, list) and all(_string(x) for x in v)


# key -> (check, description of what is expected)
SCHEMA = {
    "robot": (_string, "a built-in robot name or a path"),
    "base": (_string, "a link name"),
    "tip": (_string, "a link name"),
    "tips": (_string_list, "a list of link names"),
    "data": (_string, "a path to a CSV or .xlsx file"),
    "columns": (_string, "a path to a column map (YAML, docs/file-formats.md)"),
    "validation_data": (_string, "a path to a measurement file"),
    "verify": (_string, "a path to a thresholds file (YAML)"),
    "out": (_string, "a folder path"),
    "device": (lambda v: v in ("position", "pose"), "'position' or 'pose'"),
    "marker": (lambda v: (isinstance(v, int) and not isinstance(v, bool) and v >= 1) or _string(v), "a marker number >= 1"),
    "joints": (_string_list, "a list of column names"),
    "units": (lambda v: isinstance(v, dict), "a mapping {length: m|mm, angle: rad|deg}"),
    "holdout": (lambda v: _number(v) and 0 <= v < 1, "a number in [0, 1)"),
    "seed": (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
    "solver": (lambda v: v in SOLVERS, f"one of {', '.join(SOLVERS)}"),
    "free": (_string_list, "a list of parameter names"),
    "known": (_string_list, "a list of device parameter names or prefixes"),
    "sigma_position": (lambda v: _number(v) and v > 0, "a positive number (m)"),
    "sigma_orientation": (lambda v: _number(v) and v > 0, "a positive number (rad)"),
    "max_steps": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v > 0, "a positive integer"),
    "rtol": (lambda v: _number(v) and v > 0, "a positive number"),
    "atol": (lambda v: _number(v) and v > 0, "a positive number"),
}
PATH_KEYS = ("robot", "data", "columns", "validation_data", "verify", "out")
UNITS = {"length": ("m", "mm"), "angle": ("rad", "deg")}


def _parse(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        if path.lower().endswith(".toml"):
            doc = tomllib.loads(raw.decode("utf-8-sig"))
        else:
            doc = load_yaml(raw)
    except (tomllib.TOMLDecodeError, yaml.YAMLError, UnicodeDecodeError) as exc:
        kind = "TOML" if path.lower().endswith(".toml") else "YAML"
        raise ConfigError(f"{path}: not valid {kind}: {' '.join(str(exc).split())}") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping of option: value at the top level")
    return doc


def validate(doc: dict, path: str = "<config>") -> dict:
    """Check keys and values; returns a copy with units flattened to length_unit / angle_unit."""
    out = {}
    for key, value in doc.items():
        if key not in SCHEMA:
            raise ConfigError(f"{path}: unknown key {key!r}{suggestion(str(key), SCHEMA)}; known keys: {', '.join(SCHEMA)}")
        check, expected = SCHEMA[key]
        if not check(value):
            raise ConfigError(f"{path}: key {key!r} must be {expected}, got {value!r}")
        if key in ("joints", "free", "known") and duplicates(value):
            raise ConfigError(f"{path}: key {key!r}: {duplicates(value)[0]!r} given twice")
        if key == "units":
            for kind, unit in value.items():
                if kind not in UNITS or unit not in UNITS[kind]:
                    raise ConfigError(f"{path}: key 'units.{kind}' must be one of "
                                      f"{UNITS.get(kind, 'length/angle')}, got {unit!r}")
                out[f"{kind}_unit"] = unit
        else:
            out[key] = value
    return out


def load_config(path: str) -> dict:
    """The validated job options of a YAML/TOML file; relative paths are made relative to its folder
    (a `robot` value that is not an existing file is left as is: a built-in name)."""
    path = str(path)
    if not os.path.exists(path):
        raise ConfigError(f"{path}: no such file")
    job = validate(_parse(path), path)
    here = os.path.dirname(os.path.abspath(path))
    for key in PATH_KEYS:
        if key in job and not os.path.isabs(job[key]):
            candidate = os.path.join(here, job[key])
            if key != "robot" or os.path.exists(candidate):
                job[key] = candidate
    return job


__all__ = ["ConfigError", "SCHEMA", "load_config", "validate"]
