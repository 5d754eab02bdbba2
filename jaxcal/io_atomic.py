"""Atomic output: every file is written to a temp file in its own folder, then renamed over the
target (os.replace), so a reader or a crash never sees a half-written file."""

from __future__ import annotations

import contextlib
import json
import os
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


__all__ = ["OutputError", "atomic_path", "check_not_input", "write_json_atomic", "write_text_atomic"]
