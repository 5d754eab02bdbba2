"""Lowered programs kept across processes (`jax.export`), so that a second process skips tracing them.

The persistent compilation cache (`jaxcal.xla_cache`) skips XLA's compile, but each process still traces
and lowers every program it runs: the TALOS solver's trace and lowering took 1.0 s of a 5 s warm
`jaxcal calibrate`. When a cache folder is enabled, `lower` keeps each program exported by `jax.export`
(serialized StableHLO) in `<folder>/exported`, under a fingerprint of everything its trace reads; a later
process deserializes it and lowers only the call of it (0.2 s for that solver, compile served by the
compilation cache). Entries are `AtomicFileCache` files: written by rename, checked by SHA-256 on read.
Functions run on their own outside the solvers (the closure programs of `jaxcal.closure`) are decorated with
`jit` (`KeptJit`): their programs for concrete arguments are kept the same way (the Delta's closure solve
took 1.8-2.4 s to trace for each sample count of a warm `jaxcal calibrate delta`).

A stale program would give a wrong answer silently, so the fingerprint (SHA-256) is conservative:
jaxcal's source (every .py file of the package), the jax and jaxlib versions, the backend, the jax
settings that change lowering (x64, matmul precision, promotion rules), the function's name, its static
arguments by their pickled content (the robot, device and settings: their arrays, names and structure)
and the shapes and dtypes of its array arguments. Static arguments whose pickle refers to code outside
jaxcal, jax, numpy and the standard library (a user's device class or function, whose code the
fingerprint cannot see), or that cannot be pickled, are not cached: those programs are traced every
time, as without a cache. So is a program `jax.export` cannot serialize, and an entry that cannot be
read back (a folder shared with an installation without flatbuffers) is traced again.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import io
import pathlib
import pickle
import types

import jax
import jaxlib
import numpy as np

from jaxcal import compiled
from jaxcal.xla_cache import AtomicFileCache

# Top-level packages whose code a pickled static argument may name: their code is covered by the versions
# and the source digest in the fingerprint (or does not change within one Python).
KNOWN_CODE = frozenset({"jaxcal", "jax", "jaxlib", "numpy", "optimistix", "equinox", "lineax", "builtins",
                        "collections", "functools", "operator", "math", "copyreg", "_codecs", "types"})

# jax settings read while tracing and lowering (dtypes, precision of products, promotion rules)
LOWERING_CONFIG = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion")

_FOLDER: list[pathlib.Path | None] = [None]


def use_folder(folder: str | pathlib.Path | None) -> None:
    """Keep exported programs in `folder`/exported (made at the first program kept); None: none kept."""
    _FOLDER[0] = pathlib.Path(folder) / "exported" if folder else None


@functools.lru_cache(maxsize=4)
def _cache_in(folder: pathlib.Path) -> AtomicFileCache:
    return AtomicFileCache(folder)


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """SHA-256 of every .py file of the jaxcal package (path and content), in path order."""
    root = pathlib.Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


class _UnknownCode(Exception):
    """A static argument names code the fingerprint cannot see."""


class _CheckedPickler(pickle.Pickler):
    """A pickler that refuses functions and classes from outside KNOWN_CODE."""

    def reducer_override(self, obj):
        if isinstance(obj, (type, types.FunctionType, types.BuiltinFunctionType, types.MethodType)):
            module = getattr(obj, "__module__", None) or ""
            if module.partition(".")[0] not in KNOWN_CODE or "<locals>" in getattr(obj, "__qualname__", ""):
                raise _UnknownCode(f"{module}.{getattr(obj, '__qualname__', obj)}")
        return NotImplemented


def _content(obj) -> bytes | None:
    """The pickled content of the static arguments, or None when the fingerprint cannot cover them."""
    buf = io.BytesIO()
    try:
        _CheckedPickler(buf, protocol=5).dump(obj)
    except (_UnknownCode, pickle.PicklingError, TypeError, AttributeError, RecursionError):
        return None
    return buf.getvalue()


def signature(tree) -> tuple:
    """What selects a compiled program among arguments: the tree's structure and each leaf's shape, dtype and
    weak typing (numpy and JAX arrays of one shape and dtype alike)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return (treedef, *((np.shape(v), _dtype_code(v), bool(getattr(v, "weak_type", False))) for v in leaves))


def _dtype_code(v) -> str:
    """The leaf's dtype as numpy's code ("<f8"): str(dtype) runs numpy's Python __str__, ~1 us, and one `identify`
    takes ~750 signatures of leaves (0.8 of its 26 ms, Stanford arm, 200 poses)."""
    dtype = getattr(v, "dtype", None)
    return (dtype if dtype is not None else np.result_type(v)).str


def placements(tree) -> tuple[str, ...]:
    """The placements (shardings) of the tree's arrays committed to devices other than the default one, sorted:
    a program for those is lowered for them and not kept. (Outputs of a compiled program are committed to the
    device they were computed on: the default one, which is no placement.)"""
    default = jax.config.jax_default_device or jax.devices()[0]
    return tuple(sorted({str(v.sharding) for v in jax.tree_util.tree_leaves(tree)
                         if isinstance(v, jax.Array) and not isinstance(v, jax.core.Tracer) and v.committed
                         and v.devices() != {default}}))


def lowering_config() -> str:
    """The jax settings that change how a traced program is lowered."""
    return repr([getattr(jax.config, name) for name in LOWERING_CONFIG])


def fingerprint(fn, args: tuple, static: dict) -> str | None:
    """The cache key of `fn(*args, **static)`'s program, or None when it must not be cached."""
    content = _content(sorted(static.items()))
    if content is None:
        return None
    h = hashlib.sha256()
    for part in (source_digest(), jax.__version__, jaxlib.__version__, jax.default_backend(), lowering_config(),
                 f"{fn.__module__}.{fn.__qualname__}", repr(signature(args))):
        h.update(part.encode())
        h.update(b"\0")
    h.update(content)
    return h.hexdigest()


def lower(fn, args: tuple, static: dict):
    """`fn.lower(*args, **static)` (fn a `jax.jit` function, `static` its static arguments), through the
    exported-program cache when a folder is in use and the program can be fingerprinted and serialized."""
    key = fingerprint(fn, args, static) if _FOLDER[0] is not None else None
    return _lower_kept(key, lambda: jax.export.export(fn)(*args, **static), lambda: fn.lower(*args, **static), args)


def _lower_kept(key: str | None, export, plain, dynamic: tuple):
    """The program under `key` read back from the folder (or exported by `export()` and kept there), lowered
    for the arguments `dynamic`; `plain()` (the plain jit's lowering) when it cannot be kept."""
    try:
        cache = _cache_in(_FOLDER[0]) if key is not None else None
    except OSError:  # the folder cannot be made (read-only, a file in the way): nothing kept
        cache = None
    if cache is None:
        return plain()
    blob = cache.get(key)
    program = _read(blob)
    if program is None:
        if blob is not None:  # an entry that cannot be read back: replaced by this one
            with contextlib.suppress(OSError):
                cache.entry(key).unlink()
        try:
            program = export()
            blob = program.serialize()
        except (ValueError, NotImplementedError, ImportError):  # a custom call without a stable ABI; no flatbuffers
            return plain()
        with contextlib.suppress(OSError):  # a full disk loses the entry, not the calibration
            cache.put(key, blob)
    return jax.jit(program.call).lower(*dynamic)


def _read(blob: bytes | None):
    """The exported program of a cache entry, or None (no entry, or one this installation cannot read)."""
    if blob is None:
        return None
    try:
        return jax.export.deserialize(blob)
    except Exception:  # flatbuffers missing, or bytes that are no program (struct.error, AttributeError, ...): a miss
        return None


class KeptJit:
    """`jax.jit(fn, static_argnums=...)` whose programs for concrete arguments are kept like the solvers' (`lower`):
    with a folder in use, a call with arrays (not tracers) runs an executable compiled from the program read
    back from the folder, or exported and kept there at its first call. Equal static arguments (by content, the
    fingerprint) share one program across processes; in a process, executables are looked up by the static
    arguments themselves, the argument shapes and the jax settings that change lowering, as jax.jit does (at
    most MAX_KEPT per function). Under a trace (called inside another program), without a folder, or with
    arrays committed to a device other than the default one, it is the plain jit. Outputs that are NamedTuples
    must be registered (`jax.export.register_namedtuple_serialization`), else the program is not kept."""

    MAX_KEPT = 32

    def __init__(self, fn, static_argnums: tuple[int, ...]):
        self.jitted = jax.jit(fn, static_argnums=static_argnums)
        self.static_argnums = tuple(static_argnums)
        functools.update_wrapper(self, fn)
        self._executables: collections.OrderedDict = collections.OrderedDict()
        compiled.register(self._executables.clear)

    def __call__(self, *args):
        if _FOLDER[0] is None:
            return self.jitted(*args)
        static = tuple(args[i] for i in self.static_argnums)
        dynamic = tuple(a for i, a in enumerate(args) if i not in self.static_argnums)
        if placements(dynamic) or any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(dynamic)):
            return self.jitted(*args)
        key = (static, signature(dynamic), lowering_config())
        exe = self._executables.get(key)
        if exe is None:
            exe = self._executables[key] = self._compile(args, static, dynamic)
            if len(self._executables) > self.MAX_KEPT:
                self._executables.popitem(last=False)
        else:
            self._executables.move_to_end(key)
        return exe(*dynamic)

    def _compile(self, args: tuple, static: tuple, dynamic: tuple):
        key = fingerprint(self.jitted, dynamic, {"static_argnums": static})
        return _lower_kept(key, lambda: jax.export.export(self.jitted)(*args), lambda: self.jitted.lower(*args),
                           dynamic).compile()


def jit(static_argnums: tuple[int, ...] = ()):
    """Decorator: `KeptJit(fn, static_argnums)`, for functions run on their own (not only inside a solver)
    whose tracing is a noticeable part of a run (the Delta's closure: 1.8-2.4 s each shape)."""
    return lambda fn: KeptJit(fn, static_argnums)
