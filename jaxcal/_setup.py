"""Process-wide JAX settings: float64 everywhere; a persistent compilation cache only on request.

Importing jaxcal keeps no compiled code on disk unless JAXCAL_CACHE names a folder (or is 1, for
~/.cache/jaxcal/xla) or `jaxcal.enable_compilation_cache` is called. The cache is
`jaxcal.xla_cache.AtomicFileCache` (entries written by rename and checked by SHA-256 on read), so
concurrent and killed processes can share a folder. The `jaxcal` command turns it on by default
(`cli.cache_folder`).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see shared JAX_NOTES pitfall 1

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

DEFAULT_CACHE_DIR = os.path.join(os.path.expanduser("~"), ".cache", "jaxcal", "xla")


def enable_compilation_cache(path: str | None = None) -> str:
    """Keep compiled XLA code in `path` (default ~/.cache/jaxcal/xla) across processes, and the lowered solvers
    in its subfolder exported (`jaxcal.exported`); returns the folder."""
    from jaxcal.exported import use_folder
    from jaxcal.xla_cache import install

    path = path or DEFAULT_CACHE_DIR
    install(path)
    use_folder(path)
    return path


def cache_dir_from_env(value: str | None) -> str | None:
    """The cache folder JAXCAL_CACHE asks for: None when unset, empty or 0; the default folder for 1."""
    if value in (None, "", "0"):
        return None
    return DEFAULT_CACHE_DIR if value == "1" else value


if cache_dir_from_env(os.environ.get("JAXCAL_CACHE")):
    enable_compilation_cache(cache_dir_from_env(os.environ.get("JAXCAL_CACHE")))
