"""Command line: `jaxcal calibrate | compare | identifiable | simulate | diagnose | cv | bench | demo` (docs/cli.md).

Every subcommand is a function of parsed arguments returning an exit code; bad input (robot
file, CSV, config, options, an unusable output path, any OS error on them) prints one `error:` line
naming the file/line/field and returns 2, never a traceback; output paths are checked before any
work. Outputs go to files written atomically, never over an input; `calibrate` replaces its output
folder as a set and removes its staging folder on SIGTERM (exit 143).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import os
import sys
import time
import warnings

from jaxcal._setup import DEFAULT_CACHE_DIR, cache_dir_from_env, enable_compilation_cache
from jaxcal.fit.core import SOLVERS
from jaxcal.fit.csvfile import prismatic_joints

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
# Python's cyclic collector in the console command (`run`; not when jaxcal is imported as a library): full collections
# wait for 20 collections of the middle generation, each after 50 young ones of 10,000 net allocations (default 700,
# 10, 10). Tracing and compiling make ~10^5 long-lived objects a second, and with the defaults a full collection ran
# each time they grew by a quarter: `jaxcal calibrate` on TALOS spent 0.54 s of 5.8 s (first process) and 0.39 s of
# 2.7 s (warm cache) collecting. With these: first process 5.26 -> 4.86-4.96 s, warm 2.34-2.41 -> 2.13-2.18 s
# (docs/benchmarks.md, twenty-fourth session).
CLI_GC_THRESHOLDS = (10_000, 50, 20)


def _console():
    from rich.console import Console

    return Console(stderr=True)


@contextlib.contextmanager
def _progress(enabled: bool = True):
    """A rich progress display on stderr (spinners for stages, bars for counted work)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=_console(), transient=True, disable=not enabled) as prog:
        yield prog


@contextlib.contextmanager
def _stage(prog, text):
    """A spinner for one stage; yields a function that shows what the stage is doing now beside its text."""
    task = prog.add_task(text, total=1)
    yield lambda now: prog.update(task, description=f"{text}: {now}")
    prog.update(task, completed=1)


# -- shared loading --------------------------------------------------------------------------------
def load_robot_arg(spec: str, base=None, tip=None, tips=None):
    """A built-in robot name, a robot YAML (seed table, DH table, UR kinematics) or a URDF (with base/tip links, or
    base and the tip links of a tree, `tips`, marker k of the data on tips[k])."""
    import jaxcal as jc
    from jaxcal.config import ConfigError

    if spec in jc.robots.builtin.available():
        if tips:
            raise ConfigError(f"{spec}: --tips / tips is for URDF robots (the links of a tree read by the markers)")
        return jc.robots.get(spec)
    if not os.path.exists(spec):
        raise FileNotFoundError(f"{spec}: no such robot file, and not a built-in robot ({', '.join(jc.robots.builtin.available())})")
    if spec.lower().endswith(".urdf"):
        return jc.load_robot(spec, base=base, tip=tip, tips=tips)
    if tips:
        raise ConfigError(f"{spec}: --tips / tips is for URDF robots (the links of a tree read by the markers)")
    return jc.load_robot(spec)


def _input_errors():
    """Exception types that mean bad input (reported as one line, exit code 2): the library's own input
    errors, OS errors on the files (missing, unreadable, a folder, disk full) and undecodable text."""
    import yaml

    from jaxcal.config import ConfigError
    from jaxcal.fit.data import DataError
    from jaxcal.io_atomic import OutputError
    from jaxcal.robots.io import RobotFileError

    return (ConfigError, DataError, OutputError, RobotFileError, OSError, KeyError, UnicodeError, yaml.YAMLError)


def one_line(text) -> str:
    """A message as one printable line: newlines, NUL and other control characters escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


def _say(kind: str, style: str, text) -> None:
    from rich.markup import escape

    _console().print(f"[{style}]{kind}:[/] {escape(one_line(text))}", highlight=False, markup=True, soft_wrap=True)


def _fail(exc) -> int:
    """Print one `error:` line for an input error and return exit code 2."""
    msg = str(exc)
    if type(exc).__str__ is KeyError.__str__ and exc.args:  # a plain KeyError quotes its message
        msg = str(exc.args[0])
    if isinstance(exc, OSError) and exc.filename is not None:
        msg = f"{exc.filename}: {exc.strerror or msg}"
    _say("error", "bold red", msg)  # one line: paths stay whole
    return EXIT_BAD_INPUT


def _warn(text) -> None:
    _say("warning", "bold yellow", text)


# -- calibrate ---------------------------------------------------------------------------------------
DEFAULTS = {"holdout": 0.25, "seed": 0, "solver": "lm", "out": "calib-output", "sigma_position": 1e-3,
            "sigma_orientation": 1e-3, "max_steps": 200}
JOB_KEYS = ("robot", "data", "columns", "validation_data", "verify", "base", "tip", "tips", "out", "device", "marker", "joints",
            "length_unit", "angle_unit", "holdout", "seed", "solver", "free", "known", "sigma_position", "sigma_orientation",
            "max_steps", "rtol", "atol")


def tolerances(options) -> dict:
    """{"rtol": ..., "atol": ...} of the solver tolerances given (dict or argparse namespace); the others keep
    the calibration core's defaults (`core.Settings`)."""
    get = options.get if isinstance(options, dict) else lambda k: getattr(options, k, None)
    return {k: get(k) for k in ("rtol", "atol") if get(k) is not None}


def check_options(given: dict) -> None:
    """Command-line values checked as the job file's (`jaxcal.config.SCHEMA`); errors name the option."""
    from jaxcal.config import SCHEMA, ConfigError
    from jaxcal.names import duplicates

    for key, value in given.items():
        if key in SCHEMA and not SCHEMA[key][0](value):
            raise ConfigError(f"--{key.replace('_', '-')} must be {SCHEMA[key][1]}, got {value!r}")
        if key in ("free", "known") and duplicates(value):
            raise ConfigError(f"--{key}: {duplicates(value)[0]!r} given twice")


def job_options(args) -> dict:
    """Defaults, then the config file, then the command-line options (which win)."""
    from jaxcal.config import ConfigError, load_config

    job = dict(DEFAULTS)
    if args.config:
        job.update(load_config(args.config))
    given = {key: getattr(args, key) for key in JOB_KEYS if getattr(args, key, None) is not None}
    check_options(given)
    job.update(given)
    for key in ("robot", "data"):
        if not job.get(key):
            raise ConfigError(f"calibrate: no {key} given (argument or '{key}:' in the config file)")
    if not 0 <= job["holdout"] < 1:
        raise ConfigError(f"calibrate: --holdout must be in [0, 1), got {job['holdout']}")
    return job


OUTPUTS = ("results.json", "report.md", "report.html", "errors_per_pose.png", "error_map.png", "convergence.png",
           "verdict.json")


def load_thresholds(path: str) -> dict:
    """The `--verify` thresholds: a YAML (or JSON) mapping such as `max_heldout_rms_mm: 0.5` (docs/cli.md)."""
    import yaml

    from jaxcal.config import ConfigError
    from jaxcal.textfile import read_bytes
    from jaxcal.yamlfile import load_yaml

    try:
        doc = load_yaml(read_bytes(path, ConfigError))
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(doc, dict) or not doc:
        raise ConfigError(f"{path}: --verify needs a mapping of thresholds, e.g. 'max_heldout_rms_mm: 0.5'")
    return {k: _yaml_number(v) for k, v in doc.items()}


def _yaml_number(value):
    """YAML 1.1 reads 1.0e6 (no exponent sign) as text: such a value is the number it spells."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def is_table(path: str, columns) -> bool:
    """Whether a data file is read through `Dataset.from_table` (a workbook, or any file given a column map)
    rather than `Dataset.from_csv`."""
    from jaxcal.fit.tables import WORKBOOK_SUFFIXES

    return columns is not None or str(path).lower().endswith(WORKBOOK_SUFFIXES)


def load_data(path, robot, columns=None, joints=None, device=None, marker=None, length_unit=None, angle_unit=None,
              limits=None):
    """A measurement file for `robot`: a CSV (`Dataset.from_csv`), or an .xlsx workbook or a text export with a
    column map (`--columns`, `Dataset.from_table`); joints default to the robot's, prismatic joints are the robot's."""
    import jaxcal as jc
    from jaxcal.config import ConfigError

    joints = joints or robot.joint_names
    if robot.tips and device is None:  # a tree read at several links: all the file's markers, marker k on tips[k]
        device = "multi_position"
    if not is_table(path, columns):
        return jc.Dataset.from_csv(path, joints=joints, device=device, marker=marker, length_unit=length_unit,
                                   angle_unit=angle_unit, prismatic=prismatic_joints(robot), limits=limits)
    if marker is not None:
        raise ConfigError(f"{path}: --marker / marker applies to CSV files; name the marker's columns in the column map")
    return jc.Dataset.from_table(path, columns=columns, joints=joints, device=device, length_unit=length_unit,
                                 angle_unit=angle_unit, prismatic=prismatic_joints(robot), limits=limits)


def load_job_data(job, robot):
    """The job's dataset, checked against the robot (joint columns, units against its limits); returns
    (data, warnings): the data warnings (unit doubts, constant joint columns) as strings."""
    from jaxcal.fit.csvfile import DataWarning, constant_columns, joint_limits
    from jaxcal.fit.data import DataError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataWarning)
        data = load_data(job["data"], robot, job.get("columns"), job.get("joints"), job.get("device"), job.get("marker"),
                         job.get("length_unit"), job.get("angle_unit"), joint_limits(robot))
    found = [str(w.message) for w in caught if issubclass(w.category, DataWarning)]
    try:
        data.device.check_robot(robot)
    except ValueError as exc:
        raise DataError(f"{job['data']}: {exc}") from None
    for name in constant_columns(data.q, list(data.joint_names or robot.joint_names)):
        found.append(f"{data.source}: joint column {name!r} has the same value in every sample: the data cannot identify "
                     "its offset (it stays at its nominal value)")
    return data, found


def check_enough_samples(data, holdout: float) -> None:
    """Refuse, before the fit, a training split with fewer residuals than the device's unknowns (frame and marker)
    or fewer than 3 samples (the device frame needs 3 points off one line)."""
    from jaxcal.fit.data import DataError

    n_train = int(round((1.0 - holdout) * len(data))) if holdout > 0 else len(data)
    per_sample = {"point": 3, "frame": 6}.get(data.device.marker_reading, int(math.prod(data.device.reading_shape)))
    n_dev = int(sum(data.device.free_mask))
    if n_train < 3 or n_train * per_sample <= n_dev:
        raise DataError(f"{data.source}: {len(data)} sample(s), {n_train} for the fit after holding out {holdout:g}: "
                        f"too few to fit the {n_dev} device frame/marker parameters and the robot; give more samples "
                        "(tens) or --holdout 0")


def check_known(known, device) -> None:
    """Every --known entry names device parameters (a name or a prefix such as `dev`, `tool`); else the closest names."""
    from jaxcal.names import UnknownNameError, suggestion

    prefixes = sorted({n.rsplit(".", k)[0] for n in device.names for k in range(1, n.count(".") + 1)} | set(device.names))
    for k in known:
        if not any(n == k or n.startswith(k + ".") for n in device.names):
            raise UnknownNameError(f"--known / known: {k!r} names no device parameter{suggestion(k, prefixes)}")


def check_archive(archive: str | None, out: str) -> None:
    """The --archive folder is usable and lies outside the output folder (which each run replaces)."""
    from jaxcal.config import ConfigError
    from jaxcal.io_atomic import check_writable_dir

    if archive is None:
        return
    a, o = os.path.realpath(archive), os.path.realpath(out)
    if a == o or a.startswith(o + os.sep) or o.startswith(a + os.sep):
        raise ConfigError(f"--archive {archive}: must lie outside the output folder {out} (and not contain it)")
    check_writable_dir(archive)


def job_inputs(job, config) -> dict:
    """The job's input files by role (None where not given; a built-in robot name is not a file)."""
    return {"robot": job["robot"], "data": job["data"], "validation_data": job.get("validation_data"), "config": config,
            "columns": job.get("columns"), "verify": job.get("verify")}


def export_files(robot, kinds) -> dict:
    """File name -> writer of each --export kind (`jaxcal.robots.exports.export_writers`)."""
    from jaxcal.io_atomic import safe_filename
    from jaxcal.robots.exports import export_writers

    return {f"{safe_filename(robot.name)}{suffix}": write for suffix, write in export_writers(robot, kinds).values()}


def _calibrate(args) -> int:
    from datetime import datetime, timezone

    from jaxcal.config import ConfigError
    from jaxcal.io_atomic import check_not_input, check_output_dir, cleanup_on_signals
    from jaxcal.report.job import heldout_verdict, quality_lines, run_job, supported_file_name, verify, write_job
    from jaxcal.report.provenance import archive_run, provenance
    from jaxcal.robots.io import save_robot

    started = datetime.now(timezone.utc)
    try:
        job = job_options(args)
        inputs = [job["robot"], job["data"], args.config, job.get("columns"), job.get("validation_data"), job.get("verify")]
        out = job["out"]
        for name in OUTPUTS:
            check_not_input(os.path.join(out, name), inputs)
        check_archive(args.archive, out)
        thresholds = load_thresholds(job["verify"]) if job.get("verify") else None
        if thresholds:
            try:  # unknown names and bad values fail before any work
                verify({"health": {"ok": True}}, thresholds)
            except ValueError as exc:
                raise ConfigError(f"{job['verify']}: {exc}") from None
        check_output_dir(out, inputs)  # before any work: a file, unwritable, or holding other files
        with _progress(not args.quiet) as prog:
            with _stage(prog, "loading robot and data"):
                robot = load_robot_arg(job["robot"], job.get("base"), job.get("tip"), job.get("tips"))
                data, data_warnings = load_job_data(job, robot)
            validation = None
            if job.get("validation_data"):
                validation, more = load_job_data(dict(job, data=job["validation_data"]), robot)
                data_warnings = data_warnings + more
            robot_file = calibrated_robot_file(robot)
            exports = export_files(robot, args.export or ())
            for name in [robot_file, *exports]:
                check_not_input(os.path.join(out, name), inputs)
                check_not_input(os.path.join(out, supported_file_name(name)), inputs)
            check_known(job.get("known") or (), data.device)
            free = expand_free(job.get("free"), robot)
            check_enough_samples(data, job["holdout"])
            for w in data_warnings:
                _warn(w)
            with _stage(prog, f"identifying {robot.name} on {len(data)} samples (compiles the solver on first use)") as now:
                res = run_job(robot, data, holdout=job["holdout"], seed=job["seed"], solver=job["solver"], free=free,
                              known=tuple(job.get("known") or ()), sigma_position=job["sigma_position"],
                              sigma_orientation=job["sigma_orientation"], max_steps=job["max_steps"], progress=now,
                              validation=validation, **tolerances(job))
            add_data_warnings(res.summary, data_warnings)
            if thresholds:
                res.summary["verdict"] = verify(res.summary, thresholds)
            res.summary["provenance"] = provenance(job_inputs(job, args.config), job, ["jaxcal", *getattr(args, "argv", [])], started)
            with _stage(prog, f"writing the report to {out}"), cleanup_on_signals():
                write_job(out, res, lambda path, a: save_robot(robot, path, a), robot_file, exports)
            archived = archive_run(out, args.archive, res.summary) if args.archive else None
    except _input_errors() as exc:
        return _fail(exc)
    r = res.summary["rms"]
    print(res.fit.report())
    if "heldout" in r:
        h = r["heldout"]["position_mm"]
        print(f"held-out ({res.summary['samples']['heldout']} samples): position RMS {h['before']:.4g} mm (nominal) -> "
              f"{h['after']:.4g} mm (calibrated)")
    for line in quality_lines(res.summary["quality"]):
        print(line)
    verdict = heldout_verdict(res.summary)
    if verdict:
        print(verdict)
    print(f"report: {os.path.join(out, 'report.md')}; calibrated robot: {os.path.join(out, robot_file)}")
    if archived:
        print(f"archived: {archived}")
    verdict = res.summary.get("verdict")
    if verdict is not None:
        failed = [c["check"] for c in verdict["checks"] if not c["pass"]]
        print(f"verify: {'PASS' if verdict['pass'] else 'FAIL (' + ', '.join(failed) + ')'}; "
              f"{os.path.join(out, 'verdict.json')}")
        if not verdict["pass"]:
            return 1
    return health_exit_code(res.summary["health"], args.accept_warnings)


def add_data_warnings(summary: dict, found) -> None:
    """The data checks' warnings join the job's health record (first in the report; exit 1 without --accept-warnings)."""
    if found:
        health = summary["health"]
        health["warnings"] = list(found) + list(health["warnings"])
        health["ok"] = False


def health_exit_code(health: dict, accept_warnings: bool) -> int:
    """0 when the result is healthy (or its warnings are accepted), 1 when it carries warnings (docs/cli.md)."""
    if health["ok"]:
        return 0
    if accept_warnings:
        print(f"{len(health['warnings'])} health warning(s) accepted (--accept-warnings)")
        return 0
    print(f"exit 1: {len(health['warnings'])} health warning(s) (see the first lines above and of report.md); "
          "--accept-warnings to exit 0 anyway", file=sys.stderr)
    return 1


def expand_free(patterns, robot):
    """Robot parameter names matching names or shell patterns (`*.offset`: joint offsets only);
    a pattern that matches nothing is an error naming it and the closest parameter names."""
    import fnmatch

    from jaxcal.names import UnknownNameError, suggestion

    if patterns is None:
        return None
    out = []
    for pat in patterns:
        hits = [n for n in robot.names if fnmatch.fnmatchcase(n, pat)]
        if not hits:
            raise UnknownNameError(f"--free / free: {pat!r} matches no parameter of {robot.name}{suggestion(pat, robot.names)}")
        out += [n for n in hits if n not in out]
    return out


def calibrated_robot_file(robot) -> str:
    """File name of the calibrated robot: URDF for robots that came from a URDF (a file or a
    URDF-based built-in), else YAML in the layout the robot was read in (seed table, DH table, UR kinematics).
    The robot's name comes from its file, so it passes
    through `safe_filename` (no `/`, `..`, NUL or markup reaches the file system)."""
    from jaxcal.io_atomic import safe_filename

    fmt = robot.extras.get("file_format") or robot.bodies[0].conv.file_format  # DH tables, UR kinematics: yaml
    return f"{safe_filename(robot.name)}_calibrated.{fmt}"


# -- compare ------------------------------------------------------------------------------------------
def load_results(folder: str) -> dict:
    """results.json of a `jaxcal calibrate` output folder; errors name the file."""
    import json

    from jaxcal.config import ConfigError

    path = os.path.join(folder, "results.json")
    if not os.path.isfile(path):
        raise ConfigError(f"{path}: no such file ({folder} is not a `jaxcal calibrate` output folder)")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except ValueError as exc:
        raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("robot"), str) or not isinstance(doc.get("parameters"), list):
        raise ConfigError(f"{path}: not the results of `jaxcal calibrate` (no 'robot' or 'parameters')")
    return doc


def _compare(args) -> int:
    from jaxcal.config import ConfigError
    from jaxcal.io_atomic import check_output_file, write_text_atomic
    from jaxcal.report.html import compare_html

    try:
        check_output_file(args.out, "--out file")
        a, b = load_results(args.run_a), load_results(args.run_b)
        if a["robot"] != b["robot"]:
            raise ConfigError(f"{os.path.join(args.run_b, 'results.json')}: robot {b['robot']!r}, but "
                              f"{os.path.join(args.run_a, 'results.json')} is of robot {a['robot']!r}: runs of different "
                              "robots cannot be compared")
        write_text_atomic(args.out, compare_html(a, b, args.run_a, args.run_b))
    except _input_errors() as exc:
        return _fail(exc)
    print(f"comparison of {args.run_a} and {args.run_b}: {args.out}")
    return 0


# -- identifiable --------------------------------------------------------------------------------------
def _identifiable(args) -> int:
    import jaxcal as jc
    from jaxcal.io_atomic import check_output_file, write_json_atomic

    try:
        if args.json:
            check_output_file(args.json, "--json file")
        robot = load_robot_arg(args.robot, args.base, args.tip, getattr(args, "tips", None))
        with _progress(not args.quiet) as prog, _stage(prog, f"observation matrix of {args.method} ({args.n} samples)"):
            res = jc.identifiable(robot, args.method, n_configs=args.n, seed=args.seed, include_gains=not args.no_gains)
    except _input_errors() + (ValueError,) as exc:
        return _fail(exc)
    print(f"{robot.name}, method {res.method}: {res.count} identifiable parameters of {robot.n_params}")
    print(f"base set: {', '.join(res.names)}")
    if res.extra:
        print(f"also identified (method unknowns): {', '.join(res.extra)}")
    if res.no_effect:
        print(f"no effect: {', '.join(res.no_effect)}")
    for rel in res.regroup:
        print(f"regrouped: {rel}")
    print("observability: " + ", ".join(f"{k} {v:.4g}" for k, v in res.indices.items()))
    if args.json:
        write_json_atomic(args.json, {"robot": robot.name, "method": res.method, "count": res.count, "names": res.names,
                                      "extra": res.extra, "no_effect": res.no_effect, "regrouped": res.regrouped,
                                      "regroup": res.regroup, "indices": res.indices, "condition": res.condition})
    return 0


# -- simulate ---------------------------------------------------------------------------------------------
def _simulate(args) -> int:
    import numpy as np

    import jaxcal as jc
    from jaxcal.io_atomic import check_not_input, check_output_file, write_json_atomic

    try:
        check_output_file(args.out, "--out file")
        if args.truth:
            check_output_file(args.truth, "--truth file")
        robot = load_robot_arg(args.robot, args.base, args.tip, getattr(args, "tips", None))
        check_not_input(args.out, [args.robot])
        if args.truth:
            check_not_input(args.truth, [args.robot])
        a_true = jc.perturb(robot, {"length": args.perturb_mm * 1e-3, "angle": args.perturb_mrad * 1e-3}, seed=args.seed)
        q = jc.random_configurations(robot, args.n, seed=args.seed + 1, margin=0.05)
        noise = {"position": args.noise_mm * 1e-3, "orientation": args.noise_mrad * 1e-3}
        data = jc.simulate(robot, a_true, q, args.device, noise=noise, seed=args.seed + 2)
        if args.temperature:
            data.covariates["temperature"] = 20.0 + np.random.default_rng(args.seed).uniform(0, 5, len(data))
        data.to_csv(args.out, length_unit=args.length_unit, angle_unit=args.angle_unit, prismatic=prismatic_joints(robot))
        if args.truth:
            write_json_atomic(args.truth, {"robot": robot.name, "names": robot.names, "a_true": np.asarray(a_true),
                                           "noise": noise, "seed": args.seed})
    except _input_errors() + (ValueError,) as exc:
        return _fail(exc)
    print(f"wrote {len(data)} simulated {args.device} samples of {robot.name} to {args.out}")
    return 0


# -- diagnose -----------------------------------------------------------------------------------------------
def _diagnose(args) -> int:
    import jaxcal as jc
    from jaxcal.io_atomic import check_not_input, check_writable_dir, write_json_atomic

    try:
        import jaxcal.gap  # noqa: F401
    except ImportError as exc:
        _console().print(f"[bold red]error:[/] `jaxcal diagnose` needs the gap-diagnosis module jaxcal.gap, "
                         f"which is not available in this installation ({exc})")
        return 1
    try:
        check_writable_dir(args.out)
        robot = load_robot_arg(args.robot, args.base, args.tip, getattr(args, "tips", None))
        data = load_data(args.data, robot, args.columns, device=args.device, marker=args.marker,
                         length_unit=args.length_unit, angle_unit=args.angle_unit)
        check_not_input(os.path.join(args.out, "diagnosis.json"), [args.robot, args.data, args.columns])
        with _progress(not args.quiet) as prog, _stage(prog, f"diagnosing the sim-to-real gap of {robot.name}"):
            d = jc.gap.diagnose(robot, data, folds=args.folds, seed=args.seed, max_steps=args.max_steps, solver=args.solver,
                                sigma_position=args.sigma_position, sigma_orientation=args.sigma_orientation,
                                **tolerances(args))
            payload = d.to_dict()
        print(d.report())
        os.makedirs(args.out, exist_ok=True)
        d.plot(args.out)
        write_json_atomic(os.path.join(args.out, "diagnosis.json"), payload)
    except _input_errors() as exc:
        return _fail(exc)
    return 0


# -- cv -----------------------------------------------------------------------------------------------------
def _cv(args) -> int:
    from jaxcal.fit.cv import cross_validate
    from jaxcal.io_atomic import check_not_input, check_output_file, write_json_atomic

    try:
        if args.json:
            check_output_file(args.json, "--json file")
        robot = load_robot_arg(args.robot, args.base, args.tip, getattr(args, "tips", None))
        data = load_data(args.data, robot, args.columns, device=args.device, marker=args.marker,
                         length_unit=args.length_unit, angle_unit=args.angle_unit)
        if args.json:
            check_not_input(args.json, [args.robot, args.data, args.columns])
        with _progress(not args.quiet) as prog, _stage(prog, f"{args.folds}-fold cross-validation of {robot.name}"):
            res = cross_validate(robot, data, folds=args.folds, seed=args.seed, sigma_position=args.sigma_position,
                                 sigma_orientation=args.sigma_orientation, max_steps=args.max_steps, solver=args.solver,
                                 **tolerances(args))
    except _input_errors() + (ValueError,) as exc:
        return _fail(exc)
    print(res.report())
    for row in res.per_fold:
        print(f"  fold {row['fold'] + 1}: {row['samples']} held-out samples, {row['heldout_before']:.4g} -> "
              f"{row['heldout_after']:.4g}" + (f"; {len(row['warnings'])} warning(s)" if row["warnings"] else ""))
    if args.json:
        write_json_atomic(args.json, res.to_dict())
    ok = res.healthy_folds == res.folds
    return health_exit_code({"ok": ok, "warnings": [w for r in res.per_fold for w in r["warnings"]]}, args.accept_warnings)


# -- bench ------------------------------------------------------------------------------------------------
def quick_bench(robot_name: str = "stanford", n_fk: int = 10000, n_fit: int = 100, repeats: int = 5, progress=None) -> dict:
    """Built-in timing: batched forward kinematics and one identification; compile apart, medians."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxcal as jc

    rb = jc.robots.get(robot_name)
    q = jnp.asarray(jc.random_configurations(rb, n_fk, seed=0))
    fk = jax.jit(lambda a, q: jc.forward(rb, a, q).p)
    t = time.perf_counter()
    fk_exe = fk.lower(rb.nominal, q).compile()
    fk_compile = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fk_exe(rb.nominal, q))
        times.append(time.perf_counter() - t)
        if progress:
            progress()
    data = jc.simulate(rb, jc.perturb(rb, 1e-3, seed=1), jc.random_configurations(rb, n_fit, seed=2), "position", noise=1e-5)
    fits = []
    for _ in range(repeats):
        fits.append(jc.identify(rb, data, sigma_position=1e-5))
        if progress:
            progress()
    return {"robot": robot_name, "fk": {"n": n_fk, "compile_s": fk_compile, "median_s": float(np.median(times)),
                                        "configs_per_s": float(n_fk / np.median(times))},
            "identify": {"samples": n_fit, "parameters": len(fits[0].estimated), "compile_s": fits[0].timings["compile_s"],
                         "median_run_s": float(np.median([f.timings["run_s"] for f in fits[1:]] or [fits[0].timings["run_s"]])),
                         "rms_after_mm": fits[-1].rms_after}}


def _benchmarks_dir():
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks")


def _bench(args) -> int:
    import runpy

    from jaxcal.io_atomic import check_output_file, write_json_atomic

    if args.json:
        check_output_file(args.json, "--json file")
    if args.script:
        path = os.path.join(_benchmarks_dir(), args.script if args.script.endswith(".py") else args.script + ".py")
        if not os.path.exists(path):
            avail = sorted(f[:-3] for f in os.listdir(_benchmarks_dir()) if f.endswith(".py") and not f.startswith("_")) \
                if os.path.isdir(_benchmarks_dir()) else []
            listing = ", ".join(avail) or "none: not a source checkout"
            return _fail(FileNotFoundError(f"{path}: no such benchmark (available: {listing})"))
        saved_argv, saved_path = sys.argv, list(sys.path)
        sys.argv, sys.path = [path] + list(args.script_args), [os.path.dirname(path)] + sys.path  # scripts import _common
        try:
            runpy.run_path(path, run_name="__main__")
        finally:
            sys.argv, sys.path[:] = saved_argv, saved_path
        return 0
    with _progress(not args.quiet) as prog:
        task = prog.add_task("quick benchmark (FK batch, identification)", total=2 * args.repeats)
        res = quick_bench(args.robot, args.n_fk, args.n_fit, args.repeats, progress=lambda: prog.advance(task))
    fk, fi = res["fk"], res["identify"]
    print(f"{res['robot']}: forward kinematics of {fk['n']} configurations: compile {fk['compile_s']:.2f} s, "
          f"run {fk['median_s'] * 1e3:.2f} ms (median), {fk['configs_per_s'] / 1e6:.2f} M configs/s")
    print(f"identification ({fi['samples']} samples, {fi['parameters']} parameters): compile {fi['compile_s']:.2f} s, "
          f"run {fi['median_run_s'] * 1e3:.1f} ms (median), RMS after {fi['rms_after_mm']:.4f} mm")
    if args.json:
        write_json_atomic(args.json, res)
    return 0


# -- demo -------------------------------------------------------------------------------------------------
def _demo(args) -> int:
    from jaxcal.demo import run

    run(args.out)
    return 0


# -- parser -------------------------------------------------------------------------------------------------
def _robot_args(p):
    p.add_argument("robot", help="built-in robot name, robot YAML or URDF")
    p.add_argument("--base", help="URDF: first link of the chain")
    p.add_argument("--tip", help="URDF: last link of the chain")
    p.add_argument("--tips", nargs="+", metavar="LINK", help="URDF: the links of a tree read by markers 1, 2, ... of the data "
                   "(a link once per marker on it; shared links are estimated once)")


def _solver_args(p, solver_default="lm", max_steps_default=200, max_steps_help="200"):
    """The calibration core's solver settings, the same on every command that fits (`core.Settings`)."""
    p.add_argument("--solver", choices=tuple(SOLVERS), default=solver_default,
                   help=f"least-squares solver (default {solver_default or 'lm'})")
    p.add_argument("--max-steps", dest="max_steps", type=positive_int, default=max_steps_default,
                   help=f"solver step limit (default {max_steps_help}); a diagnosis whose baseline stops at it says so and "
                        "names no effect")
    p.add_argument("--rtol", type=positive_float, help="solver relative tolerance (default: the core's)")
    p.add_argument("--atol", type=positive_float, help="solver absolute tolerance (default: the core's)")


def _data_args(p):
    p.add_argument("--columns", metavar="MAP.yaml", help="column map of an .xlsx workbook or a tracker/mocap text export: "
                   "which column is which quantity, units, angle convention (docs/file-formats.md)")
    p.add_argument("--device", choices=("position", "pose"), help="reading type (default: from the CSV columns)")
    p.add_argument("--marker", help="marker number when the CSV has x1.., x2.. columns (default: the first)")
    p.add_argument("--length-unit", dest="length_unit", choices=("m", "mm"), help="unit of x, y, z (default: header line, else m)")
    p.add_argument("--angle-unit", dest="angle_unit", choices=("rad", "deg"),
                   help="unit of joint angles and rotation vectors (default: header line, else rad)")


def _quiet(p):
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")


class Parser(argparse.ArgumentParser):
    """argparse with the CLI's error format: one `error:` line on stderr, exit code 2."""

    def error(self, message):
        _say("error", "bold red", f"{self.prog}: {message} (see {self.prog} --help)")
        raise SystemExit(EXIT_BAD_INPUT)


def _number_type(kind, test, expected):
    """An argparse type: `kind(text)` that must be finite and pass `test`, else a one-line error saying `expected`."""
    def convert(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not math.isfinite(v) or not test(v):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return v
    convert.__name__ = expected
    return convert


positive_int = _number_type(int, lambda v: v > 0, "a positive integer")
nonneg_int = _number_type(int, lambda v: v >= 0, "an integer >= 0")
positive_float = _number_type(float, lambda v: v > 0, "a positive number")
nonneg_float = _number_type(float, lambda v: v >= 0, "a number >= 0")
finite_float = _number_type(float, lambda v: True, "a finite number")
fraction = _number_type(float, lambda v: 0 <= v < 1, "a number in [0, 1)")
folds_int = _number_type(int, lambda v: v >= 2, "an integer >= 2")


def export_kinds(text: str) -> tuple[str, ...]:
    """An argparse type: a comma-separated list of `jaxcal.robots.exports.EXPORT_KINDS`."""
    from jaxcal.robots.exports import EXPORT_KINDS

    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in kinds if k not in EXPORT_KINDS]
    if bad or not kinds:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(EXPORT_KINDS)}, got {text!r}")
    return tuple(dict.fromkeys(kinds))


def cache_folder(option: str | None, no_cache: bool, env: str | None) -> str | None:
    """Where the command keeps compiled code: --cache DIR, else none with --no-cache or JAXCAL_CACHE=0,
    else JAXCAL_CACHE's folder, else the default folder (the cache is safe to share: jaxcal.xla_cache)."""
    if option:
        return option
    if no_cache or env in ("", "0"):
        return None
    return cache_dir_from_env(env) or DEFAULT_CACHE_DIR


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="jaxcal", description="Differentiable robot calibration in JAX.")
    cache = p.add_mutually_exclusive_group()
    cache.add_argument("--cache", metavar="DIR", help="folder of the compiled XLA code kept across runs "
                       f"(default {DEFAULT_CACHE_DIR}, or JAXCAL_CACHE; safe to share between concurrent runs)")
    cache.add_argument("--no-cache", action="store_true", help="keep no compiled code on disk (as JAXCAL_CACHE=0)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    c = sub.add_parser("calibrate", help="identify a robot from a measurement CSV; write results, report, calibrated robot")
    c.add_argument("robot", nargs="?", help="built-in robot name, robot YAML or URDF (or 'robot:' in --config)")
    c.add_argument("data", nargs="?", help="measurement CSV, .xlsx workbook or text export (docs/file-formats.md) "
                   "(or 'data:' in --config)")
    c.add_argument("--config", help="YAML or TOML job file (keys as these options; the options given here win)")
    c.add_argument("--validation-data", dest="validation_data", metavar="FILE",
                   help="a second measurement file of the same set-up, evaluated with the calibration (never fitted)")
    c.add_argument("--verify", metavar="THRESHOLDS.yaml", help="pass/fail thresholds (max_heldout_rms_mm, "
                   "max_validation_rms_mm, max_train_rms_mm, max_heldout_orientation_mrad, max_condition_number, "
                   "require_health_ok); writes verdict.json and exits 1 on FAIL")
    c.add_argument("--base", help="URDF: first link of the chain")
    c.add_argument("--tip", help="URDF: last link of the chain")
    c.add_argument("--tips", nargs="+", metavar="LINK", help="URDF: the links of a tree read by markers 1, 2, ... of the data "
                   "(a link once per marker on it; shared links are estimated once)")
    c.add_argument("--out", help="output folder (default calib-output)")
    _data_args(c)
    c.add_argument("--holdout", type=fraction, help="fraction of samples held out of the fit (default 0.25)")
    c.add_argument("--seed", type=int, help="seed of the held-out split (default 0)")
    c.add_argument("--free", nargs="+", help="robot parameters to estimate, names or patterns such as '*.offset' "
                   "(default: all free; the base set of them is identified)")
    c.add_argument("--known", nargs="+", help="device parameters (or prefixes dev, tool) taken as known")
    c.add_argument("--sigma-position", dest="sigma_position", type=positive_float, help="position noise in m (residual weight)")
    c.add_argument("--sigma-orientation", dest="sigma_orientation", type=positive_float, help="orientation noise in rad")
    _solver_args(c, None, None)  # defaults from the job file, else DEFAULTS
    c.add_argument("--accept-warnings", dest="accept_warnings", action="store_true",
                   help="exit 0 even when the result carries health warnings (default: exit 1)")
    c.add_argument("--export", type=export_kinds, metavar="KINDS", help="more robot files, each also in a >= 2 sigma "
                   "variant (URDF robots): urdf-rising (joint offsets in <calibration rising> tags), pal-yaml (PAL's "
                   "calibration YAML); comma-separated")
    c.add_argument("--archive", metavar="DIR", help="also copy the finished output folder to DIR/<UTC time>-<config hash>/ "
                   "and add a line to DIR/index.jsonl")
    _quiet(c)
    c.set_defaults(func=_calibrate)

    k = sub.add_parser("compare", help="compare two calibration runs (output folders): RMS and parameter differences as HTML")
    k.add_argument("run_a", metavar="RUN_A", help="output folder of a `jaxcal calibrate` run")
    k.add_argument("run_b", metavar="RUN_B", help="output folder of another run of the same robot")
    k.add_argument("--out", default="compare.html", help="HTML file to write (default compare.html)")
    k.set_defaults(func=_compare)

    i = sub.add_parser("identifiable", help="identifiable parameters of a robot for a calibration method (GECARO §3)")
    _robot_args(i)
    i.add_argument("--method", default="position", help="position, location, point_link, frame_link, plane1_known, "
                   "plane1_unknown, plane2_known, plane2_unknown, distance (default position)")
    i.add_argument("--n", type=positive_int, default=60, help="number of generated samples (default 60)")
    i.add_argument("--seed", type=int, default=0)
    i.add_argument("--no-gains", action="store_true", help="do not identify transmission gains")
    i.add_argument("--json", help="also write the result as JSON here")
    _quiet(i)
    i.set_defaults(func=_identifiable)

    s = sub.add_parser("simulate", help="write a CSV of simulated measurements of a perturbed robot")
    _robot_args(s)
    s.add_argument("--out", required=True, help="CSV file to write")
    s.add_argument("--n", type=positive_int, default=100, help="number of samples (default 100)")
    s.add_argument("--device", choices=("position", "pose"), default="position")
    s.add_argument("--perturb-mm", dest="perturb_mm", type=nonneg_float, default=1.0,
                   help="std of the length errors (default 1 mm)")
    s.add_argument("--perturb-mrad", dest="perturb_mrad", type=nonneg_float, default=2.0,
                   help="std of the angle errors (default 2 mrad)")
    s.add_argument("--noise-mm", dest="noise_mm", type=nonneg_float, default=0.02, help="measurement noise std (default 0.02 mm)")
    s.add_argument("--noise-mrad", dest="noise_mrad", type=nonneg_float, default=0.02,
                   help="orientation noise std (default 0.02 mrad)")
    s.add_argument("--length-unit", dest="length_unit", choices=("m", "mm"), default="m")
    s.add_argument("--angle-unit", dest="angle_unit", choices=("rad", "deg"), default="rad")
    s.add_argument("--temperature", action="store_true", help="add a temperature covariate column")
    s.add_argument("--truth", help="also write the true parameters as JSON here")
    s.add_argument("--seed", type=nonneg_int, default=0)
    s.set_defaults(func=_simulate)

    d = sub.add_parser("diagnose", help="diagnose the sim-to-real gap left after calibration (jaxcal.gap)")
    _robot_args(d)
    d.add_argument("data", help="measurement CSV, .xlsx workbook or text export")
    d.add_argument("--out", default="diagnosis-output", help="output folder (default diagnosis-output)")
    _data_args(d)
    d.add_argument("--folds", type=folds_int, default=5, help="cross-validation folds (default 5)")
    d.add_argument("--seed", type=int, default=0, help="seed of the fold split (default 0)")
    _solver_args(d, max_steps_default=None, max_steps_help="1000 for the baselines, 200 for the refits")
    d.add_argument("--sigma-position", dest="sigma_position", type=positive_float,
                   help="instrument noise in m per axis: the noise floor and the noise test when there are no repeated poses")
    d.add_argument("--sigma-orientation", dest="sigma_orientation", type=positive_float, help="instrument orientation noise in rad")
    _quiet(d)
    d.set_defaults(func=_diagnose)

    v = sub.add_parser("cv", help="k-fold cross-validation of the calibration of a robot on a measurement CSV")
    _robot_args(v)
    v.add_argument("data", help="measurement CSV, .xlsx workbook or text export")
    _data_args(v)
    v.add_argument("--folds", type=folds_int, default=5, help="folds (default 5; repeated poses stay in one fold)")
    v.add_argument("--seed", type=int, default=0, help="seed of the fold split (default 0)")
    v.add_argument("--sigma-position", dest="sigma_position", type=positive_float, default=1e-3, help="position noise in m")
    v.add_argument("--sigma-orientation", dest="sigma_orientation", type=positive_float, default=1e-3, help="orientation noise in rad")
    _solver_args(v)
    v.add_argument("--json", help="write the per-fold results as JSON here")
    v.add_argument("--accept-warnings", dest="accept_warnings", action="store_true",
                   help="exit 0 even when a fold's fit carries health warnings (default: exit 1)")
    _quiet(v)
    v.set_defaults(func=_cv)

    b = sub.add_parser("bench", help="quick built-in timing, or run one of the repository's benchmarks/ scripts")
    b.add_argument("--script", help="benchmark script in benchmarks/ (fk, identify, ga, ...); arguments after --")
    b.add_argument("script_args", nargs="*", help="arguments passed to the script")
    b.add_argument("--robot", default="stanford")
    b.add_argument("--n-fk", dest="n_fk", type=positive_int, default=10000)
    b.add_argument("--n-fit", dest="n_fit", type=positive_int, default=100)
    b.add_argument("--repeats", type=positive_int, default=5)
    b.add_argument("--json", help="also write the timings as JSON here")
    _quiet(b)
    b.set_defaults(func=_bench)

    m = sub.add_parser("demo", help="calibrate MRR-1 and the Stanford arm on simulated data, print a report, write plots")
    m.add_argument("--out", default="demo-output", help="folder for the report and plots (default: demo-output)")
    m.set_defaults(func=_demo)
    return p


def main(argv=None) -> int:
    """Run one command; exit codes 0 (ok), 1 (health warnings), 2 (bad input or an OS error on a file: one
    `error:` line), 130 (Ctrl-C), 143 (SIGTERM while writing; the staging folder is removed)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        args.argv = list(sys.argv[1:] if argv is None else argv)
    except SystemExit as exc:  # a bad option: one `error:` line printed, exit code 2 returned (--help still exits)
        if not exc.code:
            raise
        return int(exc.code) if isinstance(exc.code, int) else EXIT_BAD_INPUT
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        folder = cache_folder(args.cache, args.no_cache, os.environ.get("JAXCAL_CACHE"))
        if folder:
            enable_compilation_cache(folder)
        return args.func(args)
    except _input_errors() as exc:  # anything a subcommand did not catch itself
        return _fail(exc)
    except KeyboardInterrupt:
        _say("error", "bold red", "interrupted")
        return EXIT_INTERRUPTED


def run() -> None:
    """The `jaxcal` console command: `main()`, then leave without Python's teardown of the interpreter.

    Every output is written (atomically) and closed when `main` returns; tearing down jax/XLA, scipy and
    matplotlib object by object took 0.55-0.65 s of a 5.5 s warm `jaxcal calibrate` on TALOS. So the
    output streams and log handlers are flushed, pending jax effects awaited, and the process ends with
    `os._exit` (its exit code that of `main`). Under a profiler or a tracer (`python -m cProfile`, coverage),
    whose results are written at exit, it exits the usual way.

    The modules imported so far (jax, numpy, jaxcal's core) live to the end: they are frozen out of the cyclic
    collector's generations, and its thresholds raised (CLI_GC_THRESHOLDS)."""
    gc.freeze()
    gc.set_threshold(*CLI_GC_THRESHOLDS)
    code = main() or 0
    if sys.gettrace() is not None or sys.getprofile() is not None:
        sys.exit(code)
    import logging

    import jax

    jax.effects_barrier()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a reader that has gone (`jaxcal ... | head`), a closed stream
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
