"""Atomic output: every file is written to a temp file in its own folder, then renamed over the
target (os.replace), so a reader or a crash never sees a half-written file. A set of files (the
`jaxcal calibrate` output folder) is staged in a hidden folder beside its target and swapped in
whole (`replace_folder`); `check_output_dir` / `check_output_file` refuse unusable output paths
before any work, and `cleanup_on_signals` removes staging folders when the process is terminated.
Names from input files become file names only through `safe_filename`."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import json
import os
import re
import shutil
import signal
import tempfile

import numpy as np


class OutputError(ValueError):
    """An output path that must not be written (e.g. it would overwrite an input)."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ".tmp"):
    """Yield a temp path beside `path`; on success it replaces `path`, on error it is removed."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix="." + os.path.basename(path) + ".", suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_text_atomic(path: str, text: str) -> str:
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)
    return path


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "tolist"):  # numpy / jax arrays and scalars
        return _jsonable(np.asarray(v).tolist())
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def write_json_atomic(path: str, obj) -> str:
    """JSON of `obj` (numpy/jax arrays become lists, NaN/inf become null), written atomically."""
    return write_text_atomic(path, json.dumps(_jsonable(obj), indent=2) + "\n")


def check_not_input(out_path: str, inputs) -> None:
    """Refuse to write `out_path` when it is one of the input files."""
    out = os.path.realpath(out_path)
    for p in inputs:
        if p and os.path.exists(p) and os.path.realpath(p) == out:
            raise OutputError(f"{out_path}: refusing to overwrite the input file {p}")


# -- names that become file names ------------------------------------------------------------------
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")
MAX_NAME = 100


def safe_filename(name, fallback: str = "robot") -> str:
    """`name` (from an input file: a robot name, a joint name) as one harmless file-name component:
    runs of anything but ASCII letters, digits and `._+-` become `_` (path separators, `..`, NUL,
    `<script>`, spaces), leading/trailing dots and underscores go (no hidden file, no `..`), at most
    100 characters; an empty result is `fallback`."""
    text = _UNSAFE.sub("_", str(name)).strip("._")[:MAX_NAME].strip("._")
    return text or fallback


# -- output paths checked before any work ----------------------------------------------------------
def _nearest_existing(path: str) -> str:
    """The path itself if it exists, else its nearest existing ancestor."""
    path = os.path.abspath(path)
    while not os.path.lexists(path):
        up = os.path.dirname(path)
        if up == path:
            break
        path = up
    return path


def _probe_writable(folder: str, what: str) -> None:
    """Create and remove a hidden folder in `folder` (the honest test: permissions, read-only mounts, quotas)."""
    try:
        probe = tempfile.mkdtemp(dir=folder, prefix=".jaxcal-probe-")
        os.rmdir(probe)
    except OSError as exc:
        raise OutputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None


def _creatable_in(path: str, what: str) -> None:
    """The nearest existing ancestor of `path` is a folder we can write in."""
    anc = _nearest_existing(os.path.dirname(os.path.abspath(path)))
    if not os.path.isdir(anc):
        raise OutputError(f"{what}: {anc} is a file, not a folder")
    _probe_writable(anc, what)


def check_output_file(path: str, what: str = "output file") -> None:
    """Refuse, before any work, an output file path that is a folder or whose folder cannot be created or written."""
    path = str(path)
    if os.path.isdir(path):
        raise OutputError(f"{path}: {what} is a folder, expected a file path")
    _creatable_in(path, f"{path}: {what}")


def listed_outputs(folder: str, manifest: str = "results.json") -> list[str] | None:
    """The file names a previous jaxcal run lists in `folder/manifest` ("files"), or None when it has none."""
    path = os.path.join(folder, manifest)
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, ValueError):
        return None
    files = doc.get("files") if isinstance(doc, dict) else None
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return files + [manifest]


def check_writable_dir(out: str) -> None:
    """Refuse, before any work, an output folder that is a file or cannot be created or written."""
    out = str(out)
    what = f"{out}: output folder"
    if os.path.lexists(out) and not os.path.isdir(out):
        raise OutputError(f"{what} is a file (or a broken link), not a folder")
    if os.path.isdir(out):
        _probe_writable(out, what)
    else:
        _creatable_in(out, what)


def check_output_dir(out: str, inputs=(), manifest: str = "results.json") -> None:
    """Refuse, before any work, an output folder that `replace_folder` could not replace as a set:
    a file; a folder that cannot be created or written (nor the folder above it, where the new set is
    staged); the current folder or one holding it; a folder holding one of the `inputs` or files a
    previous run did not write (its `manifest` lists what it wrote), which the new set would delete."""
    out = str(out)
    what = f"{out}: output folder"
    real = os.path.realpath(out)
    if os.path.lexists(out) and not os.path.isdir(out):
        raise OutputError(f"{what} is a file (or a broken link), not a folder")
    if real == os.path.dirname(real):
        raise OutputError(f"{what} is the root folder; give a dedicated folder")
    for p in inputs:
        if p and os.path.exists(p) and os.path.realpath(p).startswith(real.rstrip(os.sep) + os.sep):
            raise OutputError(f"{what} holds the input {p}; the new results replace the whole folder: "
                              "give another output folder")
    cwd = os.path.realpath(os.getcwd())
    if cwd == real or cwd.startswith(real.rstrip(os.sep) + os.sep):
        raise OutputError(f"{what} is the current folder or holds it; give a dedicated folder (e.g. calib-output)")
    _creatable_in(real, what)
    if os.path.isdir(real):
        _probe_writable(real, what)
        entries = sorted(os.listdir(real))
        listed = set(listed_outputs(real, manifest) or ())
        foreign = [e for e in entries if e not in listed and not e.startswith(".staging-")]
        if foreign:
            raise OutputError(f"{what} holds files a previous jaxcal run did not write ({', '.join(foreign[:5])}"
                              f"{', ...' if len(foreign) > 5 else ''}); the new results replace the whole folder: "
                              "give a new or empty folder")


# -- a set of files replaced at once -----------------------------------------------------------------
_LIVE: set[str] = set()  # staging folders of this process, removed on SIGTERM
_RENAME_EXCHANGE = 2


def _exchange(a: str, b: str) -> bool:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE); False where not available."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd = -100
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0


def _swap_in(stage: str, out: str) -> None:
    """Put the folder `stage` at `out`; the previous `out` (if any) ends up at `stage` (removed by the caller)."""
    if not os.path.lexists(out):
        os.rename(stage, out)
        return
    if _exchange(stage, out):
        return
    old = tempfile.mkdtemp(dir=os.path.dirname(out), prefix=f".{os.path.basename(out)}.old-")
    os.rename(out, old)  # rename over an empty folder is allowed
    try:
        os.rename(stage, out)
    except OSError:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _signals_deferred():
    """Hold SIGTERM/SIGINT/SIGHUP back (delivered on exit) while two renames must both happen."""
    sigs = {signal.SIGTERM, signal.SIGINT, signal.SIGHUP}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (AttributeError, ValueError, OSError):
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def replace_folder(out: str, write) -> list[str]:
    """Replace the folder `out` by the files `write(stage)` creates (it returns their names) as one set.

    The files are written into a hidden folder beside `out` (`.<out>.staging-*`), which is then swapped
    with `out` in one rename (Linux renameat2; elsewhere two renames with signals held back); the previous
    folder, and so every stale file of an earlier run, is removed. On any error, or SIGTERM under
    `cleanup_on_signals`, the staging folder is removed and `out` is left as it was."""
    out = os.path.realpath(str(out))
    parent, base = os.path.split(out)
    os.makedirs(parent, exist_ok=True)
    stage = tempfile.mkdtemp(dir=parent, prefix=f".{base}.staging-")
    _LIVE.add(stage)
    try:
        names = write(stage)
        mode = os.stat(out).st_mode & 0o7777 if os.path.isdir(out) else 0o777 & ~_umask()
        os.chmod(stage, mode)  # mkdtemp creates 0700
        with _signals_deferred():
            _swap_in(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        _LIVE.discard(stage)
    return names


def _on_signal(signum, frame):
    """Remove this process's staging folders and exit with 128 + signum (finally blocks still run)."""
    for s in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_IGN)  # a second signal must not interrupt the clean-up
    for path in list(_LIVE):
        shutil.rmtree(path, ignore_errors=True)
        _LIVE.discard(path)
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def cleanup_on_signals():
    """While active, SIGTERM and SIGHUP remove the staging folders of `replace_folder` and exit with
    128 + the signal number (SIGINT raises KeyboardInterrupt, whose unwinding removes them too).
    Outside the main thread (where Python cannot install handlers) it does nothing."""
    saved = {}
    try:
        for s in (signal.SIGTERM, signal.SIGHUP):
            saved[s] = signal.signal(s, _on_signal)
    except ValueError:
        pass
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


__all__ = ["OutputError", "atomic_path", "check_not_input", "check_output_dir", "check_output_file", "check_writable_dir",
           "cleanup_on_signals",
           "listed_outputs", "replace_folder", "safe_filename", "write_json_atomic", "write_text_atomic"]
