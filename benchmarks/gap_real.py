"""Sim-to-real gap diagnosis on the public real measurements (TALOS left arm, TIAGo arm, UR10).

For each built-in real dataset (`jaxcal.realdata`, FIGAROH's examples, Apache-2.0) run
`jc.gap.diagnose` (5-fold held-out scoring, device frame and marker identified with the geometry)
and write the report, the plots and the JSON to bench-output/gap_real/<name>/, and a summary to
benchmarks/results/gap_real.json.

Run: python benchmarks/gap_real.py [talos tiago ur10]
"""

from __future__ import annotations

import json
import os
import sys
import time

import jaxcal as jc
from jaxcal.io_atomic import write_text_atomic

OUT = os.path.join("bench-output", "gap_real")
RESULTS = os.path.join("benchmarks", "results", "gap_real.json")


def run(name: str) -> dict:
    real = jc.realdata.load(name)
    t = time.perf_counter()
    d = jc.gap.diagnose(real.robot, real.data)
    wall = time.perf_counter() - t
    folder = os.path.join(OUT, name)
    d.plot(folder)
    report = d.report()
    write_text_atomic(os.path.join(folder, "report.txt"), report)
    print(f"== {name} ({len(real.data)} samples, {real.data.device.kind}), {wall:.1f} s\n{report}\n")
    top = [dict(effect=r.effect, joints=list(r.joints), before_mm=r.heldout_rms_before, after_mm=r.heldout_rms_after,
                score=r.score) for r in d.ranking[:5]]
    return dict(dataset=name, samples=len(real.data), device=real.data.device.kind, verdict=d.verdict, joints=list(d.joints),
                shrink=d.shrink, top5=top, wall_s=wall)


def main(names):
    rows = [run(n) for n in names]
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    write_text_atomic(RESULTS, json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:] or ["talos", "tiago", "ur10"])
