"""Same-process A/B of one jaxcal setting on whole `jc.identify` calls.

On this shared 2-core machine a 10 ms identify varies by 10-30 % between fresh processes run minutes apart, more than
most changes it is used to judge. Here both variants run in one process, their calls interleaved (old, new, new, old,
...), and the medians are compared. The setting is a module attribute (a constant such as `core.START_STOP`); with
--retrace, one that is read while tracing: each value's programs are compiled apart and swapped in with it.

    python benchmarks/ab_identify.py jaxcal.fit.core START_STOP 0.0 1e-6 --device pose --calls 150
"""

from __future__ import annotations

import argparse
import ast
import importlib
import time

import jax
import numpy as np

import jaxcal as jc
import jaxcal.compiled
from jaxcal.fit import core


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("module")
    p.add_argument("attribute")
    p.add_argument("old", help="a Python literal")
    p.add_argument("new", help="a Python literal")
    p.add_argument("--robot", default="stanford")
    p.add_argument("--device", default="position")
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--calls", type=int, default=100, help="calls of each variant")
    p.add_argument("--retrace", action="store_true", help="the attribute is read while tracing: compile each apart")
    a = p.parse_args()
    module = importlib.import_module(a.module)
    values = {"old": ast.literal_eval(a.old), "new": ast.literal_eval(a.new)}
    robot = jc.robots.get(a.robot)
    truth = jc.perturb(robot, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=1)
    data = jc.simulate(robot, truth, jc.random_configurations(robot, a.samples, seed=2), a.device, noise=1e-5, seed=4)
    programs, fits = {}, {}
    for name, value in values.items():
        setattr(module, a.attribute, value)
        if a.retrace:
            jaxcal.compiled.clear()
            jax.clear_caches()
        fits[name] = jc.identify(robot, data)
        jc.identify(robot, data)
        programs[name] = dict(core._COMPILED)
    times = {"old": [], "new": []}
    for k in range(a.calls):
        for name in ("old", "new") if k % 2 else ("new", "old"):
            setattr(module, a.attribute, values[name])
            if a.retrace:
                core._COMPILED.clear()
                core._COMPILED.update(programs[name])
            t = time.perf_counter()
            jc.identify(robot, data)
            times[name].append(time.perf_counter() - t)
    old, new = (float(np.median(times[n])) * 1e3 for n in ("old", "new"))
    diff = float(np.max(np.abs(np.asarray(fits["old"].a_full) - np.asarray(fits["new"].a_full))))
    print(f"{a.robot} {a.samples} {a.device}, {a.module}.{a.attribute} {a.old} -> {a.new}: medians of {a.calls} calls "
          f"{old:.3f} -> {new:.3f} ms ({new / old:.3f}x); estimates differ by {diff:.2g}; RMS after "
          f"{fits['old'].rms_after:.10g} / {fits['new'].rms_after:.10g}, iterations {fits['old'].iterations} / "
          f"{fits['new'].iterations}")


if __name__ == "__main__":
    main()
