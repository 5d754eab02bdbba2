"""Same-process A/B of two source trees of jaxcal on whole `jc.identify` calls.

`ab_identify.py` compares two values of one setting; a change that touches several functions and the compiled
program's outputs is compared here instead: jaxcal is imported from each tree in turn (the modules of the first
are dropped from `sys.modules` before the second is imported, so each package keeps its own functions, caches and
compiled programs), each fits its own copy of the same simulated data, and the calls are interleaved (old, new, new,
old, ...). On this shared 2-core machine fresh processes minutes apart differ by 10-30 %, one process by ~1-3 %.
--fresh moves the joint readings by 1e-12 rad each call, so that no evaluation is found in `core.predicted`'s cache
(what a user calibrating new data sees).

    git worktree add /tmp/old HEAD~1
    python benchmarks/ab_trees.py /tmp/old . --device pose --calls 150 --fresh
"""

from __future__ import annotations

import argparse
import copy
import importlib
import os
import sys
import time

import jax.export
import numpy as np


def registering_once(register):
    """jax.export's namedtuple registration, tolerating the second tree's registration of the same name."""

    def register_once(cls, *args, **kwargs):
        try:
            return register(cls, *args, **kwargs)
        except ValueError:  # "Duplicate serialization registration": the first tree's type keeps the name
            return cls

    return register_once


def import_tree(folder: str):
    """The jaxcal package of the source tree `folder`, imported afresh."""
    for name in [k for k in sys.modules if k == "jaxcal" or k.startswith("jaxcal.")]:
        del sys.modules[name]
    sys.path.insert(0, folder)
    try:
        jc = importlib.import_module("jaxcal")
    finally:
        sys.path.remove(folder)
    if not os.path.abspath(jc.__file__).startswith(folder):
        raise RuntimeError(f"jaxcal was imported from {jc.__file__}, not from {folder} (installed non-editable?)")
    return jc


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("old", help="source tree (the folder holding jaxcal/)")
    p.add_argument("new", help="source tree")
    p.add_argument("--robot", default="stanford")
    p.add_argument("--device", default="pose")
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--noise", type=float, default=1e-5)
    p.add_argument("--calls", type=int, default=100, help="calls of each tree")
    p.add_argument("--fresh", action="store_true", help="new joint readings (1e-12 rad apart) each call")
    a = p.parse_args()
    jax.export.register_namedtuple_serialization = registering_once(jax.export.register_namedtuple_serialization)
    trees = {}
    for label, folder in (("old", os.path.abspath(a.old)), ("new", os.path.abspath(a.new))):
        jc = import_tree(folder)
        robot = jc.robots.get(a.robot)
        truth = jc.perturb(robot, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=1)
        data = jc.simulate(robot, truth, jc.random_configurations(robot, a.samples, seed=2), a.device, noise=a.noise, seed=4)
        t = time.perf_counter()
        fit = jc.identify(robot, data)
        first = time.perf_counter() - t
        for _ in range(5):
            jc.identify(robot, data)
        trees[label] = dict(jc=jc, robot=robot, data=data, fit=fit, first=first, q=np.asarray(data.q))
    times = {"old": [], "new": []}
    for k in range(a.calls):
        for label in (("old", "new") if k % 2 else ("new", "old")):
            tree, data = trees[label], trees[label]["data"]
            if a.fresh:
                data = copy.copy(data)
                data.q = tree["q"] + 1e-12 * (k + 1)
            t = time.perf_counter()
            tree["jc"].identify(tree["robot"], data)
            times[label].append(time.perf_counter() - t)
    old, new = (float(np.median(times[label])) * 1e3 for label in ("old", "new"))
    fo, fn = trees["old"]["fit"], trees["new"]["fit"]
    moved = float(np.max(np.abs(np.asarray(fo.a_full) - np.asarray(fn.a_full))))
    print(f"{a.robot} {a.samples} {a.device}{' (new readings each call)' if a.fresh else ''}: {old:.3f} -> {new:.3f} ms "
          f"({new / old:.3f}x), medians of {a.calls} interleaved calls; first call {trees['old']['first']:.2f} / "
          f"{trees['new']['first']:.2f} s; estimates differ by {moved:.2g}; RMS after {fo.rms_after:.10g} / "
          f"{fn.rms_after:.10g}; steps {fo.iterations} / {fn.iterations}; estimated {len(fo.estimated)} / {len(fn.estimated)}")


if __name__ == "__main__":
    main()
