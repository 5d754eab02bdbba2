"""jaxcal.exported: solvers lowered once, kept in the cache folder, read back by a later run with the same
result; the fingerprint follows the content of what the trace reads, and code it cannot see is not cached."""

import copy
import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal import compiled, exported
from jaxcal.fit.core import RobotDevice, Settings, _solve_jit


@pytest.fixture
def folder(tmp_path):
    """A fresh exported-program folder for the test; the run's folder is put back after it."""
    before = exported._FOLDER[0]
    exported.use_folder(tmp_path)
    yield tmp_path / "exported"
    exported._FOLDER[0] = before
    compiled.clear()


def _fit(robot, data):
    compiled.clear()  # each fit lowers its solver again: from the trace or from the folder
    return jc.identify(robot, data, known=("dev", "tool"))


@pytest.mark.parametrize("name", ["mrr1", "fourbar2d"])  # an open chain (reverse mode), a closed loop (forward mode)
def test_a_solver_read_back_from_the_folder_gives_the_same_fit(name, folder, monkeypatch):
    rb = jc.robots.get(name)
    a_true = jc.perturb(rb, 1e-3, seed=1)
    data = jc.simulate(rb, a_true, jc.random_configurations(rb, 24, seed=2), "position", noise=1e-5, seed=3)
    first = _fit(rb, data)
    kept = sorted(folder.iterdir())
    assert kept, "the solver was not kept"
    read = []
    monkeypatch.setattr(jax.export, "deserialize", lambda blob, _d=jax.export.deserialize: read.append(1) or _d(blob))
    again = _fit(rb, data)
    assert read and sorted(folder.iterdir()) == kept  # read back, nothing new written
    exported.use_folder(None)
    traced = _fit(rb, data)
    for fit in (again, traced):
        np.testing.assert_array_equal(np.asarray(fit.a), np.asarray(first.a))
        assert fit.iterations == first.iterations and fit.converged == first.converged


def _static(robot, device="position", settings=Settings()):
    return dict(model=RobotDevice(robot, jc.make_device(device)), settings=settings, batched=())


ARGS = (np.zeros(3), {"q": np.zeros((10, 6))}, np.asarray(0, np.int32))


def test_the_fingerprint_follows_content_not_identity():
    rb = jc.robots.get("stanford")
    key = exported.fingerprint(_solve_jit, ARGS, _static(rb))
    assert key is not None and len(key) == 64
    assert exported.fingerprint(_solve_jit, ARGS, _static(copy.deepcopy(rb))) == key  # an equal copy: same program
    moved = dataclasses.replace(rb, nominal_np=rb.nominal_np + 1e-12)
    others = [_static(moved), _static(rb, "pose"), _static(rb, settings=Settings(rtol=1e-7)),
              _static(jc.robots.get("mrr1"))]
    keys = {exported.fingerprint(_solve_jit, ARGS, s) for s in others}
    keys.add(exported.fingerprint(_solve_jit, (np.zeros(3), {"q": np.zeros((11, 6))}, ARGS[2]), _static(rb)))
    keys.add(exported.fingerprint(_solve_jit, (np.zeros(3, np.float32), *ARGS[1:]), _static(rb)))
    with jax.numpy_rank_promotion("raise"):  # a setting that changes lowering
        keys.add(exported.fingerprint(_solve_jit, ARGS, _static(rb)))
    assert len(keys) == 7 and key not in keys  # seven different programs, none the first


class UserDevice(type(jc.make_device("position"))):
    """A device defined outside jaxcal: its code is not in the fingerprint."""


def test_code_the_fingerprint_cannot_see_is_not_cached():
    rb = jc.robots.get("stanford")
    user = dict(model=RobotDevice(rb, UserDevice.build()), settings=Settings(), batched=())
    assert exported.fingerprint(_solve_jit, ARGS, user) is None
    assert exported.fingerprint(_solve_jit, ARGS, _static(rb) | {"settings": lambda: 0}) is None


@pytest.mark.parametrize("name", ["stanford", "mrr1", "delta", "fourbar3d", "kiwibot", "talos_left_arm", "ur10"])
def test_every_built_in_robot_can_be_fingerprinted(name):
    """A built-in robot that could not be fingerprinted would silently never be kept."""
    assert exported.fingerprint(_solve_jit, ARGS, _static(jc.robots.get(name))) is not None


def test_a_folder_that_cannot_be_written_keeps_nothing_and_fails_nothing(tmp_path):
    """A cache folder whose exported/ cannot be made (a file in the way), a write that fails (full disk), an
    entry that is no program: the program is lowered as without a cache."""
    from jaxcal.fit import core

    blocked = tmp_path / "blocked"
    blocked.write_text("a file, not a folder")
    before = exported._FOLDER[0]
    x0, args = np.zeros(2), {"v": np.ones(3)}
    f = jax.jit(lambda x, a, limit: x * a["v"].sum() + limit)
    try:
        exported.use_folder(blocked)
        assert float(exported.lower(f, (x0, args, core.step_limit(0)), {}).compile()(x0, args, core.step_limit(0))[0]) == 0.0
        exported.use_folder(tmp_path / "full")
        full = exported._cache_in(tmp_path / "full" / "exported")
        full.put = lambda key, value: (_ for _ in ()).throw(OSError(28, "No space left on device"))
        assert exported.lower(f, (x0 + 1, args, core.step_limit(0)), {}).compile()(x0 + 1, args, core.step_limit(0))[0] == 3.0
        assert not list((tmp_path / "full" / "exported").iterdir())
        exported.use_folder(tmp_path / "odd")  # an entry that is no program: traced again, and replaced
        odd = exported._cache_in(tmp_path / "odd" / "exported")
        key = exported.fingerprint(f, (x0, args, core.step_limit(0)), {})
        odd.put(key, b"not a program")
        assert exported.lower(f, (x0, args, core.step_limit(0)), {}).compile()(x0, args, core.step_limit(0))[0] == 0.0
        assert jax.export.deserialize(odd.get(key)).call(x0, args, core.step_limit(0))[0] == 0.0
    finally:
        exported._FOLDER[0] = before


class Pair(NamedTuple):
    scaled: jax.Array
    total: jax.Array


jax.export.register_namedtuple_serialization(Pair, serialized_name="tests.test_exported.Pair")


@exported.jit(static_argnums=(0,))
def _kept(settings: Settings, x):
    return Pair(settings.max_steps * x, jnp.sum(x))


def test_a_kept_function_is_read_back_for_equal_static_arguments_and_plain_under_a_trace(folder, monkeypatch):
    """`exported.jit`: the first call with arrays keeps its program; a call after `compiled.clear` with an equal (a
    new) static argument (a jaxcal object: one from outside jaxcal is not kept) reads it back instead of exporting
    again; inside another program it is the plain jit (nothing kept for the traced call); arrays committed to the
    default device (a compiled program's outputs) use the same executable, a lowering setting another one; results
    as `jax.jit`'s, NamedTuple output included."""
    x = jnp.arange(3.0)
    first = _kept(Settings(max_steps=2), x)
    kept = sorted(folder.iterdir())
    assert len(kept) == 1 and isinstance(first, Pair)
    compiled.clear()
    monkeypatch.setattr(jax.export, "export", lambda *a, **k: pytest.fail("exported again instead of read back"))
    again = _kept(Settings(max_steps=2), x)
    traced = jax.jit(lambda v: _kept(Settings(max_steps=3), v))(x)
    assert sorted(folder.iterdir()) == kept
    monkeypatch.undo()
    on_default = jax.device_put(x, jax.devices()[0])  # committed, as a compiled program's outputs are
    assert on_default.committed and exported.placements((on_default, x)) == ()
    np.testing.assert_array_equal(_kept(Settings(max_steps=2), on_default).scaled, again.scaled)
    assert len(_kept._executables) == 1  # the same executable
    with jax.numpy_rank_promotion("raise"):  # a setting that changes lowering: another program
        _kept(Settings(max_steps=2), x)
    assert len(_kept._executables) == 2 and len(list(folder.iterdir())) == 2
    plain = _kept.jitted(Settings(max_steps=2), x)
    for out in (first, again):
        np.testing.assert_array_equal(out.scaled, plain.scaled)
        assert float(out.total) == 3.0
    np.testing.assert_array_equal(traced.scaled, 3.0 * x)


def test_closure_programs_kept_give_the_plain_results(folder):
    """The closure's own programs (`jaxcal.closure.core._solve_batched`, `_tool_of_solution`) through the folder:
    the same tool poses, closure status and free joints, bit for bit, as without a folder."""
    rb = jc.robots.get("fourbar2d")
    a = jnp.asarray(jc.perturb(rb, 1e-3, seed=1))
    q = jnp.asarray(jc.random_configurations(rb, 12, seed=2))
    kept_pose, kept_status = jc.closure.forward_with_status(rb, a, q)
    kept_solution = jc.closure.solve(rb, a, q)
    assert len(list(folder.iterdir())) == 2
    exported.use_folder(None)
    plain_pose, plain_status = jc.closure.forward_with_status(rb, a, q)
    plain_solution = jc.closure.solve(rb, a, q)
    for kept, plain in ((kept_pose, plain_pose), (kept_solution, plain_solution)):
        for u, v in zip(kept, plain):
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    np.testing.assert_array_equal(np.asarray(kept_status), np.asarray(plain_status))
