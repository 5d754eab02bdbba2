"""Process-wide JAX settings: float64 everywhere; a persistent compilation cache only on request.

The cache is off unless JAXCAL_CACHE names a folder (or is 1, for ~/.cache/jaxcal/xla) or
`jaxcal.enable_compilation_cache` is called: jax writes cache entries in place, without a
temporary file and rename, so a process killed mid-write or a concurrent reader can see a torn
entry.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see shared JAX_NOTES pitfall 1

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

DEFAULT_CACHE_DIR = os.path.join(os.path.expanduser("~"), ".cache", "jaxcal", "xla")


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA code in `path` (default ~/.cache/jaxcal/xla) across processes; returns the folder."""
    path = path or DEFAULT_CACHE_DIR
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path


def cache_dir_from_env(value: str | None) -> str | None:
    """The cache folder JAXCAL_CACHE asks for: None when unset, empty or 0; the default folder for 1."""
    if value in (None, "", "0"):
        return None
    return DEFAULT_CACHE_DIR if value == "1" else value


if cache_dir_from_env(os.environ.get("JAXCAL_CACHE")):
    enable_compilation_cache(cache_dir_from_env(os.environ.get("JAXCAL_CACHE")))
