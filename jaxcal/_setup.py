"""Process-wide JAX settings: float64 everywhere and a persistent compilation cache."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see shared JAX_NOTES pitfall 1

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def enable_compilation_cache(path: str | None = None) -> str:
    """Use a persistent XLA cache (default ~/.cache/jaxcal/xla, or $JAXCAL_CACHE)."""
    path = path or os.environ.get("JAXCAL_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "jaxcal", "xla")
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return path


if os.environ.get("JAXCAL_NO_CACHE") != "1":
    try:
        enable_compilation_cache()
    except OSError:  # read-only home: run without the cache
        pass
