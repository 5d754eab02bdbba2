"""A persistent XLA compilation cache that survives crashed and concurrent processes.

jax's own file cache (jax 0.10) writes each entry straight into its final file, so a process killed while
writing leaves a torn entry that every later process reads, and a reader racing a writer can read half a file.
`AtomicFileCache` keeps the same layout (one file per cache key) with two rules:

- put: the value and its SHA-256 are written to a temporary file in the same folder, flushed, and renamed onto
  `<key>.xla` (`os.replace`, atomic on POSIX and Windows). A reader sees no file or a whole one; two writers of
  the same key both write whole files and the last rename wins (both hold the same executable).
- get: the SHA-256 is checked; a short, torn or altered entry is a miss (and is removed), so jax compiles again.

Temporary files left by killed writers are removed when the cache is opened if they are more than an hour old.
A read touches the entry, so `remove_unused` can drop what no run has used for a while.

jax has no public hook for a cache backend: `install` sets jax's compilation-cache module state
(`jax._src.compilation_cache._cache`), checked against jax 0.10.2. If that module changes, `install` raises
`RuntimeError` and the caller runs without a persistent cache.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import tempfile
import time

from jax._src import compilation_cache as _jax_cc
from jax._src.compilation_cache_interface import CacheInterface

SUFFIX = ".xla"
TMP_PREFIX = ".tmp-"
DIGEST = 32  # bytes of SHA-256
STALE_TMP_S = 3600.0


class AtomicFileCache(CacheInterface):
    """One file per key: value followed by its SHA-256; written by rename, verified on read."""

    def __init__(self, path: str | os.PathLike):
        self._path = pathlib.Path(path)
        self._path.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(self._path, STALE_TMP_S)

    def entry(self, key: str) -> pathlib.Path:
        if not key or "/" in key or key.startswith("."):
            raise ValueError(f"bad cache key {key!r}")
        return self._path / f"{key}{SUFFIX}"

    def get(self, key: str) -> bytes | None:
        path = self.entry(key)
        try:
            data = path.read_bytes()
        except OSError:
            return None
        value, digest = data[:-DIGEST], data[-DIGEST:]
        if len(data) <= DIGEST or hashlib.sha256(value).digest() != digest:
            path.unlink(missing_ok=True)
            return None
        with contextlib.suppress(OSError):  # the entry's age is the time since it was last used (`remove_unused`)
            os.utime(path)
        return value

    def put(self, key: str, value: bytes) -> None:
        path = self.entry(key)
        if path.exists():
            return
        fd, tmp = tempfile.mkstemp(dir=self._path, prefix=TMP_PREFIX)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(value)
                f.write(hashlib.sha256(value).digest())
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            pathlib.Path(tmp).unlink(missing_ok=True)
            raise


def remove_stale_temporaries(folder: pathlib.Path, older_than_s: float) -> None:
    """Remove temporary files of writers that died more than `older_than_s` ago."""
    now = time.time()
    for tmp in folder.glob(f"{TMP_PREFIX}*"):
        try:
            if now - tmp.stat().st_mtime > older_than_s:
                tmp.unlink()
        except OSError:
            pass


def remove_unused(folder: str | os.PathLike, older_than_s: float) -> int:
    """Remove the entries (in `folder` and its subfolders) neither written nor read for `older_than_s`;
    returns how many. A process reading one at that moment gets a miss and compiles again."""
    now, removed = time.time(), 0
    for entry in pathlib.Path(folder).rglob(f"*{SUFFIX}"):
        try:
            if now - entry.stat().st_mtime > older_than_s:
                entry.unlink()
                removed += 1
        except OSError:
            pass
    return removed


def install(path: str | os.PathLike) -> AtomicFileCache:
    """Make `AtomicFileCache(path)` jax's persistent compilation cache for this process (every entry kept)."""
    import jax

    state = ("_cache", "_cache_initialized", "_cache_checked", "_cache_used", "_cache_initialized_mutex", "reset_cache")
    if not all(hasattr(_jax_cc, name) for name in state):
        raise RuntimeError("this jax version has no compilation-cache module state that jaxcal knows how to set")
    cache = AtomicFileCache(path)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    _jax_cc.reset_cache()  # jax decides once per process whether a cache is used: decide again
    with _jax_cc._cache_initialized_mutex:
        _jax_cc._cache = cache
        _jax_cc._cache_initialized = True
    return cache
