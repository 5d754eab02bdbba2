"""Sim-to-real gap diagnosis on the public real measurements (TALOS left arm, TIAGo arm, UR10).

For each built-in real dataset (`jaxcal.realdata`, FIGAROH's examples, Apache-2.0) run
`jc.gap.diagnose` (5-fold held-out scoring, device frame and marker identified with the geometry)
and write the report, the plots and the JSON to bench-output/gap_real/<name>/, and a summary to
benchmarks/results/gap_real.json. The gravity effects use the URDF inertials of the robots; with
--default-masses the robot's inertials are dropped, so they use the default mass model (1 kg at each
body origin), written to bench-output/gap_real_default_masses/ and results/gap_real_default_masses.json.

With --seed K the folds are cut with seed K (default 0) and the results go to gap_real_seedK (does a finding
survive another cut of the same samples?); --max-steps N sets the LM steps of every fit (default diagnose's 200).

Run: python benchmarks/gap_real.py [--default-masses] [--seed K] [--max-steps N] [talos tiago ur10]
"""

from __future__ import annotations

import json
import os
import sys
import time

import jaxcal as jc
from jaxcal.io_atomic import write_text_atomic


def without_inertials(robot):
    """The robot without its URDF inertials: the gap effects fall back to the default mass model."""
    return robot.replace(name=f"{robot.name} (default masses)",
                         extras={k: v for k, v in robot.extras.items() if k != "inertia"})


def run(name: str, out: str, default_masses: bool, seed: int = 0, max_steps: int = 200) -> dict:
    real = jc.realdata.load(name)
    robot = without_inertials(real.robot) if default_masses else real.robot
    t = time.perf_counter()
    d = jc.gap.diagnose(robot, real.data, seed=seed, max_steps=max_steps)
    wall = time.perf_counter() - t
    folder = os.path.join(out, name)
    d.plot(folder)
    report = d.report()
    write_text_atomic(os.path.join(folder, "report.txt"), report)
    print(f"== {name} ({len(real.data)} samples, {real.data.device.kind}), {wall:.1f} s\n{report}\n")
    top = [dict(effect=r.effect, joints=list(r.joints), before_mm=r.heldout_rms_before, after_mm=r.heldout_rms_after,
                score=r.score) for r in d.ranking[:5]]
    return dict(dataset=name, samples=len(real.data), device=real.data.device.kind, mass_model=d.mass_model, verdict=d.verdict,
                joints=list(d.joints), selected=[dict(effect=e, joints=list(j)) for e, j in d.selected], shrink=d.shrink,
                heldout_rms_before_mm=d.heldout_rms_before, heldout_rms_after_mm=d.heldout_rms_after, noise_floor_mm=d.noise_floor,
                noise_source=d.noise_source, structure_p=d.structure_p, parameters=d.parameters, diverged=d.diverged, top5=top,
                seed=seed, max_steps=max_steps, wall_s=wall)


def main(args):
    default_masses = "--default-masses" in args
    option = (lambda flag, default: int(args[args.index(flag) + 1]) if flag in args else default)  # noqa: E731
    seed, max_steps = option("--seed", 0), option("--max-steps", 200)
    values = {args[args.index(f) + 1] for f in ("--seed", "--max-steps") if f in args}
    names = [a for a in args if not a.startswith("--") and a not in values] or ["talos", "tiago", "ur10"]
    tag = ("gap_real_default_masses" if default_masses else "gap_real") + (f"_seed{seed}" if seed else "")
    rows = [run(n, os.path.join("bench-output", tag), default_masses, seed, max_steps) for n in names]
    results = os.path.join("benchmarks", "results", f"{tag}.json")
    os.makedirs(os.path.dirname(results), exist_ok=True)
    write_text_atomic(results, json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
