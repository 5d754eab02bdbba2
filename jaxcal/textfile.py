"""Input files read whole as bytes, each reader raising its own error type (DataError, RobotFileError, ...)."""

from __future__ import annotations

import os


def read_bytes(path: str, error: type[Exception]) -> bytes:
    """The bytes of the file at `path`; a missing or unreadable file raises `error` naming the path."""
    if not os.path.exists(path):
        raise error(f"{path}: no such file")
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None


__all__ = ["read_bytes"]
