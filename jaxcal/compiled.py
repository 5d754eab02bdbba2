"""Compiled code held by this process, and how to let it go.

Every XLA executable on CPU keeps its machine code in a few memory mappings (about 7.6 per executable
measured with jax 0.10.2: 300 small jitted functions added 2,300 lines to /proc/self/maps). Linux caps the
mappings of a process (`vm.max_map_count`, 65,530 by default); a process that has compiled ~8,000
executables and keeps them all is aborted by the next compile (LLVM cannot map the new code: "Fatal Python
error: Aborted" inside `backend_compile_and_load`). A long test worker or a study that builds many robots
gets there. jax's own caches keep every executable it compiled; jaxcal's caches of compiled solvers keep
theirs. `clear` empties both; `mapped_regions` says how close the process is.
"""

from __future__ import annotations

import gc
from typing import Callable

import jax

_CLEARERS: list[Callable[[], None]] = []


def register(clear: Callable[[], None]) -> Callable[[], None]:
    """Add a function that empties one of jaxcal's caches of compiled functions (e.g. an lru_cache's cache_clear)."""
    _CLEARERS.append(clear)
    return clear


def clear() -> None:
    """Drop every compiled executable jaxcal and jax hold (they are compiled again when next needed)."""
    for c in _CLEARERS:
        c()
    jax.clear_caches()
    gc.collect()


def mapped_regions() -> int:
    """Memory mappings of this process (lines of /proc/self/maps); -1 where there is no /proc."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return -1
