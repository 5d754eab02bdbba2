"""Time and memory of one gap diagnosis on many samples (issue 21 item 7: 2500 samples within 60 s and 1 GB
after compile).

    python benchmarks/gap_scale.py [--robot stanford|ur10] [--device pose|position] [--n 2500] [--repeat 2]
                                   [--out benchmarks/results/gap_scale.json]

Data: simulated, no effect, 0.05 mm / 0.05 mrad noise, geometry perturbed 1 mm / 2 mrad, the tracker frame
4 m away and rotated 150 degrees (the set-up of tests/test_core.py). The first call compiles every solver and
kernel of the diagnosis ("first"); the later calls reuse them ("run", median over --repeat). Peak RSS is the
process high-water mark (resource.getrusage): after the first call it includes compilation; the "run" figure
is the high-water mark's growth over the later calls, and the absolute mark after them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import jaxcal as jc  # noqa: E402

NOISE = 5e-5


def peak_rss_mb() -> float:
    """High-water mark of this process' resident memory (MB; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def far_frame(device, seed=0):
    """Device parameters: the frame 4 m away, rotated 150 degrees about a generic axis, a 5 cm marker offset."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    d = np.zeros(device.n_params)
    d[:3] = rng.normal(size=3)
    d[:3] *= 4.0 / np.linalg.norm(d[:3])
    d[3:6] = np.deg2rad(150.0) * axis / np.linalg.norm(axis)
    d[6:9] = [0.02, -0.03, 0.05]
    return d


def case(robot_name: str, kind: str, n: int, seed: int = 0):
    rb = jc.robots.get(robot_name)
    a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=seed + 1)
    dev = jc.make_device(kind)
    q = jc.random_configurations(rb, n, seed=seed + 2)
    data = jc.simulate(rb, a_true, q, dev, noise={"position": NOISE, "orientation": NOISE}, device_params=far_frame(dev),
                       seed=seed + 3)
    return rb, data


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="stanford")
    ap.add_argument("--device", default="pose")
    ap.add_argument("--n", type=int, default=2500)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--max-steps", type=int, default=200)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rb, data = case(args.robot, args.device, args.n)
    rss0 = peak_rss_mb()
    t = time.perf_counter()
    d = jc.gap.diagnose(rb, data, max_steps=args.max_steps)
    first = time.perf_counter() - t
    rss_first = peak_rss_mb()
    runs, stages = [], []
    for _ in range(args.repeat):
        t = time.perf_counter()
        d = jc.gap.diagnose(rb, data, max_steps=args.max_steps)
        runs.append(time.perf_counter() - t)
        stages.append(d.timings)
    rss_run = peak_rss_mb()
    out = {"robot": args.robot, "device": args.device, "n": args.n, "verdict": d.verdict,
           "heldout_rms_before_mm": d.heldout_rms_before, "noise_floor_mm": d.noise_floor,
           "first_call_s": first, "run_median_s": statistics.median(runs) if runs else None, "runs_s": runs,
           "compile_s_estimate": first - (statistics.median(runs) if runs else 0.0),
           "peak_rss_before_mb": rss0, "peak_rss_after_first_mb": rss_first, "peak_rss_after_runs_mb": rss_run,
           "rss_growth_in_runs_mb": rss_run - rss_first, "timings_last_run": stages[-1] if stages else d.timings}
    print(json.dumps(out, indent=1, default=float))
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1, default=float)
    return out


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
