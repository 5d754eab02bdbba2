import ctypes.util
import faulthandler
import gc
import os
import subprocess
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# The suite is bound by XLA compile time, and XLA:CPU's older elemental code generator compiles the same HLO faster
# than its MLIR fusion emitters (Stanford arm, identify, 200 poses: XLA 2.8 -> 1.8 s; the closure test files
# 359 -> 237 s on two workers, every test passing), while the code it makes can run slower (that identify call:
# 62 -> 90 ms). LLVM's optimisation level 0 halves the rest (the Stanford arm's residual and Jacobian: XLA 1.25 ->
# 0.63 s; the code runs ~3x slower: 2.2 -> 7.4 ms): five closure and identify test files, two workers, fresh
# cache, 244 -> 155 s, every test passing. The tests check results, not speed, so they compile with both; the
# library compiles its solver with the first (`core.CPU_COMPILE_OPTIONS`) and everything else with XLA's defaults.
# The slow studies are bound by running their code instead: a run that selects them keeps LLVM's default level (the
# Delta's gap diagnosis, 6 refits of 192 positions batched: an LM step 0.55 s at level 2, 2.6 s at level 0; its
# backlash test was stopped unfinished after 36-58 min at level 0 and took 17.6 min at level 2, machine loaded).
# Set by the first pytest process (`pytest_configure`, before any program is compiled) and inherited by the workers,
# only where this jaxlib accepts the flags (an unknown XLA flag aborts the process), never over a user's XLA_FLAGS.
FAST_RUN_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0"
SLOW_RUN_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flags: str) -> bool:
    probe = "import jax, jax.numpy as jnp; jax.jit(lambda x: x + 1)(jnp.zeros(2)).block_until_ready()"
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    try:
        return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


# A test bound by running its compiled code rather than by compiling it takes its own jitted functions back to LLVM's
# level 2: `jax.jit(f, compiler_options=OPTIMISED)` overrides the flag for that function (the Delta closure against its
# slow numpy reference, one process, no cache: 27.7 -> 17.4 s).
OPTIMISED = {"xla_backend_optimization_level": 2}
# One persistent cache of compiled XLA code and lowered solvers for the test runs of this checkout (TEST_CACHE,
# git-ignored), set by the first pytest process (the xdist controller) and inherited by its workers through the
# environment: a program compiled by one worker is loaded by the other, and by the next run (jaxcal/xla_cache.py
# and jaxcal/exported.py make sharing safe; their keys hash the program, the flags, the jax version and, for
# the lowered solvers, jaxcal's source). A fresh clone (CI) starts empty. Entries no run has used for
# TEST_CACHE_DAYS are removed at the start of a run. Never ~/.cache; JAXCAL_CACHE=DIR names another folder,
# JAXCAL_CACHE=0 turns it off.
TEST_CACHE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".cache", "test-xla")
TEST_CACHE_DAYS = 7

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# Watchdog limits (s) of one test, set-up and tear-down included. The slowest fast test took 282 s
# at load 7-10 on the shared 2-core machine; 600 s was too short for test_fourbar3d_mc's fixture at load ~12.
WATCHDOG_FAST_S = 900
WATCHDOG_SLOW_S = 3600
_watchdog_fd = None


# A worker that keeps every executable it compiled reaches Linux's vm.max_map_count (65,530) after ~8,000 and
# is aborted by the next compile (jaxcal/compiled.py): past this many mappings the compiled code is dropped.
MAX_MAPPED_REGIONS = 30_000

# Python's cyclic collector in a test worker: a worker's heap grows by every traced function and compiled program it
# keeps, and with the default thresholds (700, 10, 10) a full collection runs each time that heap has grown by a
# quarter, ~0.4 s a time late in a run. The fast suite (two workers, fresh cache, 2026-11-30): 68-70 full collections,
# 27.4-27.7 s per worker, 31 s of collecting in all per worker; with these thresholds 8-16 full ones, 0.4-0.7 s, 5.3-5.6
# s in all, and the run took 357.5 s wall against 396.1 s. A full collection now waits for 20 collections of the middle
# generation, each after 50 young ones of 10,000 net allocations; an explicit gc.collect() (`jaxcal.compiled.clear`)
# still collects everything. Peak memory per worker was the same (4.3-4.4 GB).
GC_THRESHOLDS = (10_000, 50, 20)

# The test workers allocate with jemalloc where the system has it (Debian's libjemalloc2; `.ci/run` installs it): XLA's
# compiler spends ~20 % of its time in glibc's malloc and free (perf, the Stanford arm's solver compiled at the fast
# run's flags: _int_malloc, malloc, unlink_chunk, _int_free, malloc_consolidate, cfree). Four compile-bound test files
# (test_twists, test_grid, test_core, test_delta; two workers, fresh cache, 2026-11-30): 111.0-116.0 s wall with glibc,
# 91.6-97.5 s with jemalloc, 92.7-94.2 s with Debian's mimalloc 2.0, 99.7 s with tcmalloc, 99.0-117.4 s with mimalloc 3.4
# (the cmeel-mimalloc wheel); the whole fast suite, one worker each, both runs at once: 730 -> 685 s of CPU, peak memory
# 4.8 -> 3.9 GB (docs/benchmarks.md, twenty-fifth session). Set by the first pytest process in LD_PRELOAD, which the
# xdist workers (started after pytest_configure) and their child processes inherit; never over a user's LD_PRELOAD
# (`LD_PRELOAD= make test` runs with glibc's malloc).
TEST_ALLOCATOR = "jemalloc"


@pytest.fixture(autouse=True)
def _drop_compiled_code_near_the_mapping_limit():
    from jaxcal import compiled

    yield
    if compiled.mapped_regions() > MAX_MAPPED_REGIONS:
        compiled.clear()


def run_xla_flags(markexpr: str) -> str:
    """XLA flags of a run selecting the tests `markexpr` (pytest's -m): level 0 for the fast suite only."""
    return FAST_RUN_XLA_FLAGS if markexpr.replace('"', "'").strip() in ("not slow", "'not slow'") else SLOW_RUN_XLA_FLAGS


def pytest_configure(config):
    """Set the run's XLA flags (`run_xla_flags`) and its cache folder (TEST_CACHE), both before jaxcal is imported
    (importing it starts JAX's CPU backend, which reads XLA_FLAGS, and jaxcal reads JAXCAL_CACHE), and the workers'
    allocator (TEST_ALLOCATOR), then keep a handle on the real stderr (output capture is suspended while configuring)
    for the dumps."""
    global _watchdog_fd
    flags = run_xla_flags(config.option.markexpr or "")
    if "XLA_FLAGS" not in os.environ and _xla_accepts(flags):
        os.environ["XLA_FLAGS"] = flags
    if "LD_PRELOAD" not in os.environ and (allocator := ctypes.util.find_library(TEST_ALLOCATOR)):
        os.environ["LD_PRELOAD"] = allocator
    if "JAXCAL_CACHE" not in os.environ:
        os.makedirs(TEST_CACHE, exist_ok=True)
        os.environ["JAXCAL_CACHE"] = TEST_CACHE
        from jaxcal.xla_cache import remove_unused

        remove_unused(TEST_CACHE, TEST_CACHE_DAYS * 86400.0)
    import jaxcal  # noqa: F401  (float64)

    gc.set_threshold(*GC_THRESHOLDS)
    _watchdog_fd = os.dup(2)


def pytest_collection_finish(session):
    """Freeze what the imports and the collection made (modules, test items: they live to the end) into the
    collector's permanent generation, so that full collections no longer scan them."""
    gc.collect()
    gc.freeze()


def watchdog_limit(item) -> float:
    marker = item.get_closest_marker("watchdog")
    if marker:
        return marker.args[0]
    return WATCHDOG_SLOW_S if item.get_closest_marker("slow") else WATCHDOG_FAST_S


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item):
    """Past its limit a test dumps every thread's stack and its process exits: under xdist the
    worker is replaced and the test is rerun once (see the Makefile)."""
    faulthandler.dump_traceback_later(watchdog_limit(item), exit=True, file=_watchdog_fd)
    try:
        return (yield)
    finally:
        faulthandler.cancel_dump_traceback_later()


def central_fd(f, x, h=1e-6):
    """Central finite-difference Jacobian of f: R^n -> R^m (numpy, float64)."""
    x = np.asarray(x, float)
    f0 = np.asarray(f(x)).reshape(-1)
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (np.asarray(f(x + e)).reshape(-1) - np.asarray(f(x - e)).reshape(-1)) / (2 * h)
    return J


def rel_err(A, B):
    A, B = np.asarray(A), np.asarray(B)
    return np.linalg.norm(A - B) / max(np.linalg.norm(B), 1e-300)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
