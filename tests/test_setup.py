"""Importing jaxcal turns on float64 and leaves the persistent compilation cache off unless asked."""

import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHOW = "import jax, jaxcal; print(jax.config.jax_enable_x64, jax.config.jax_compilation_cache_dir)"


def run_python(code: str, tmp_path, **env) -> str:
    """stdout of `python -c code` in a fresh process with HOME in tmp_path and no JAXCAL_CACHE unless given."""
    clean = {k: v for k, v in os.environ.items() if k != "JAXCAL_CACHE"}
    clean |= {"HOME": str(tmp_path), "PYTHONPATH": REPO, **env}
    done = subprocess.run([sys.executable, "-c", code], env=clean, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_import_leaves_the_cache_off(tmp_path):
    assert run_python(SHOW, tmp_path) == "True None"
    assert not (tmp_path / ".cache").exists()


def test_jaxcal_cache_names_the_folder(tmp_path):
    folder = tmp_path / "xla"
    assert run_python(SHOW, tmp_path, JAXCAL_CACHE=str(folder)) == f"True {folder}"
    assert run_python(SHOW, tmp_path, JAXCAL_CACHE="1") == f"True {tmp_path / '.cache' / 'jaxcal' / 'xla'}"


def test_cli_cache_option_fills_the_folder(tmp_path):
    folder = tmp_path / "xla"
    code = ("from jaxcal.cli import main; "
            f"main(['--cache', {str(folder)!r}, 'simulate', 'mrr1', '--n', '5', '--out', {str(tmp_path / 's.csv')!r}])")
    run_python(code, tmp_path)
    assert any(folder.iterdir())


def test_a_torn_or_altered_entry_is_a_miss_and_is_removed(tmp_path):
    from jaxcal.xla_cache import DIGEST, AtomicFileCache

    cache = AtomicFileCache(tmp_path)
    cache.put("k1", b"executable bytes")
    assert cache.get("k1") == b"executable bytes"
    assert cache.get("absent") is None
    whole = cache.entry("k1").read_bytes()
    assert len(whole) == len(b"executable bytes") + DIGEST
    cache.entry("k1").write_bytes(whole[:-5])  # a writer killed mid-file
    assert cache.get("k1") is None and not cache.entry("k1").exists()
    cache.put("k1", b"executable bytes")
    cache.entry("k1").write_bytes(b"X" + whole[1:])  # one byte changed
    assert cache.get("k1") is None
    cache.entry("k2").write_bytes(b"")
    assert cache.get("k2") is None
    assert not list(tmp_path.glob(".tmp-*"))


def test_stale_temporaries_of_killed_writers_are_removed(tmp_path):
    from jaxcal.xla_cache import AtomicFileCache

    old, fresh = tmp_path / ".tmp-old", tmp_path / ".tmp-fresh"
    old.write_bytes(b"half")
    fresh.write_bytes(b"half")
    os.utime(old, (0, 0))
    AtomicFileCache(tmp_path)
    assert not old.exists() and fresh.exists()  # a fresh one may be a live writer's



def test_entries_no_run_used_for_a_while_are_removed_and_a_read_is_a_use(tmp_path):
    from jaxcal.xla_cache import AtomicFileCache, remove_unused

    cache, sub = AtomicFileCache(tmp_path), AtomicFileCache(tmp_path / "exported")
    cache.put("old", b"a")
    cache.put("read", b"b")
    sub.put("deep", b"c")
    cache.put("new", b"d")
    for entry in (cache.entry("old"), cache.entry("read"), sub.entry("deep")):
        os.utime(entry, (0, 0))
    assert cache.get("read") == b"b"  # a read marks the entry as used now
    assert remove_unused(tmp_path, 86400.0) == 2
    assert [cache.get(k) for k in ("old", "read", "new")] == [None, b"b", b"d"] and sub.get("deep") is None

COMPILE = ("import jax, jax.numpy as jnp, jaxcal; jaxcal.enable_compilation_cache({folder!r}); "
           "from jax._src import monitoring; hits = []; "
           "monitoring.register_event_listener(lambda e, **k: hits.append(e) if e.endswith('cache_hits') else None); "
           "f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + {c}); print(float(f(jnp.ones((3, 3)))[0, 0]), len(hits))")


def test_concurrent_processes_share_a_folder_and_a_later_one_reads_it(tmp_path):
    """Two processes compile the same function into one folder at once; a third loads it from there;
    a torn entry left in the folder is compiled again, not loaded."""
    folder = str(tmp_path / "xla")
    clean = {k: v for k, v in os.environ.items() if k != "JAXCAL_CACHE"} | {"HOME": str(tmp_path), "PYTHONPATH": REPO}
    code = COMPILE.format(folder=folder, c=1.0)
    procs = [subprocess.Popen([sys.executable, "-c", code], env=clean, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    entries = [e for e in os.listdir(folder) if not e.startswith(".")]
    assert entries and not [e for e in os.listdir(folder) if e.startswith(".tmp-")]
    value, hits = run_python(code, tmp_path).split()
    assert value == outs[0][0] == outs[1][0] and int(hits) >= 1
    for e in entries:
        path = os.path.join(folder, e)
        with open(path, "rb") as f:
            data = f.read()
        with open(path, "wb") as f:
            f.write(data[: len(data) // 2])
    value, hits = run_python(code, tmp_path).split()
    assert value == outs[0][0] and int(hits) == 0


def test_the_command_keeps_compiled_code_by_default_unless_told_not_to():
    from jaxcal._setup import DEFAULT_CACHE_DIR
    from jaxcal.cli import cache_folder

    assert cache_folder(None, False, None) == DEFAULT_CACHE_DIR
    assert cache_folder(None, False, "1") == DEFAULT_CACHE_DIR
    assert cache_folder(None, False, "/x") == "/x"
    assert cache_folder("/y", False, "0") == "/y"
    assert cache_folder(None, True, "/x") is None
    assert cache_folder(None, False, "0") is None


def test_clearing_compiled_code_gives_back_its_memory_mappings():
    """Each executable holds mappings (jaxcal/compiled.py); `compiled.clear` drops jax's and jaxcal's."""
    import jax
    import jax.numpy as jnp

    from jaxcal import compiled
    from jaxcal.fit import core

    if compiled.mapped_regions() < 0:
        pytest.skip("no /proc/self/maps")
    compiled.clear()
    before = compiled.mapped_regions()
    fns = [jax.jit(lambda x, k=k: jnp.sin(x) * k + jnp.cos(x @ x.T) @ x) for k in range(40)]
    for k, f in enumerate(fns):
        f(jnp.ones((3 + k, 3))).block_until_ready()
    core._COMPILED["probe"] = jax.jit(lambda x: x + 1).lower(1.0).compile()
    grown = compiled.mapped_regions()
    compiled.clear()
    assert grown - before > 100, (before, grown)
    assert compiled.mapped_regions() - before < 0.1 * (grown - before) and "probe" not in core._COMPILED


def test_a_test_worker_allocates_with_the_test_allocator_where_the_system_has_it():
    """tests/conftest.py puts TEST_ALLOCATOR (jemalloc) in LD_PRELOAD for the xdist workers: this worker has it mapped."""
    import ctypes.util

    from conftest import TEST_ALLOCATOR

    allocator = ctypes.util.find_library(TEST_ALLOCATOR)
    if "PYTEST_XDIST_WORKER" not in os.environ or allocator is None or os.environ.get("LD_PRELOAD") != allocator:
        pytest.skip("not a test worker given the allocator (no xdist, no jemalloc, or the user's own LD_PRELOAD)")
    with open("/proc/self/maps") as maps:
        assert allocator in maps.read()
