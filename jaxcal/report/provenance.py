"""Where a calibration came from, and a run archive.

`provenance(...)` is the `provenance` block of results.json: jaxcal version, the git commit of the jaxcal
source tree (null unless it is a git checkout), python / jax / numpy versions, the command line, a UTC
timestamp, the SHA-256 of every input file and `config_hash`, the SHA-256 of the canonical JSON of the
job's options (output folder left out: the same job written elsewhere has the same hash).

`archive_run(out, archive, summary)` copies a finished output folder to
`archive/<timestamp>-<config_hash[:8]>/` (copied into a hidden folder in `archive`, then renamed; an
existing entry is never replaced: a taken name gets `-2`, `-3`, ...) and appends one JSON line to
`archive/index.jsonl`.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import tempfile

TIMESTAMP_FORMAT = "%Y%m%dT%H%M%SZ"


def sha256_file(path) -> str | None:
    """Hex SHA-256 of a file's bytes; None when `path` is not a file (a built-in robot name, no file)."""
    if not path or not os.path.isfile(path):
        return None
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def canonical_json(obj) -> str:
    """JSON with sorted keys and no spaces (tuples as lists, anything else by str)."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str, ensure_ascii=True)


def config_hash(options: dict, exclude=("out",)) -> str:
    """SHA-256 of the canonical JSON of the job options without `exclude`."""
    kept = {k: v for k, v in options.items() if k not in exclude}
    return hashlib.sha256(canonical_json(kept).encode()).hexdigest()


def git_commit(folder: str, timeout: float = 5.0) -> str | None:
    """HEAD commit of the git checkout whose top folder is `folder`; None if it is none (or git is missing,
    slow or fails): a package installed inside another repository does not take that repository's commit."""
    try:
        run = lambda *a: subprocess.run(["git", "-C", folder, *a], capture_output=True, text=True, timeout=timeout,  # noqa: E731
                                        check=True).stdout.strip()
        if os.path.realpath(run("rev-parse", "--show-toplevel")) != os.path.realpath(folder):
            return None
        return run("rev-parse", "HEAD") or None
    except (OSError, subprocess.SubprocessError):
        return None


def source_tree() -> str:
    """The folder above the jaxcal package (a checkout's root when jaxcal runs from source)."""
    import jaxcal

    return os.path.dirname(os.path.dirname(os.path.abspath(jaxcal.__file__)))


def provenance(inputs: dict, options: dict, argv, now) -> dict:
    """The provenance block (module docstring); `inputs` maps a role (robot, data, ...) to a path or None,
    `now` is a timezone-aware UTC datetime."""
    import jax
    import numpy

    import jaxcal

    return {
        "jaxcal_version": jaxcal.__version__, "git_commit": git_commit(source_tree()),
        "python": platform.python_version(), "jax": jax.__version__, "numpy": numpy.__version__,
        "command_line": [str(a) for a in argv], "timestamp_utc": now.strftime(TIMESTAMP_FORMAT),
        "inputs": {role: {"path": str(p), "sha256": sha256_file(p)} for role, p in inputs.items() if p},
        "config_hash": config_hash(options),
    }


def _claim(archive: str, name: str) -> str:
    """Create and return a new empty folder `archive/name` (or `name-2`, `name-3`, ...: never an existing one)."""
    for k in range(1, 10000):
        path = os.path.join(archive, name if k == 1 else f"{name}-{k}")
        try:
            os.mkdir(path)
            return path
        except FileExistsError:
            continue
    raise FileExistsError(f"{archive}: no free archive entry name for {name}")


def archive_run(out: str, archive: str, summary: dict) -> str:
    """Copy the output folder `out` into the archive (module docstring); returns the entry's folder."""
    prov = summary["provenance"]
    os.makedirs(archive, exist_ok=True)
    tmp = tempfile.mkdtemp(dir=archive, prefix=".incoming-")
    try:
        staged = os.path.join(tmp, "run")
        shutil.copytree(out, staged)
        entry = _claim(archive, f"{prov['timestamp_utc']}-{prov['config_hash'][:8]}")
        os.rename(staged, entry)  # replaces only the empty folder claimed above
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    heldout = summary["rms"].get("heldout", {}).get("position_mm", {}).get("after")
    line = canonical_json({"timestamp_utc": prov["timestamp_utc"], "robot": summary["robot"], "data": summary["data"],
                           "heldout_rms_mm": heldout, "folder": os.path.basename(entry)})
    with open(os.path.join(archive, "index.jsonl"), "a", encoding="utf-8") as fh:
        fh.write(line + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    return entry


__all__ = ["archive_run", "canonical_json", "config_hash", "git_commit", "provenance", "sha256_file"]
