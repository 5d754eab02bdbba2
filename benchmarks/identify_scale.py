"""Time and memory of `jc.identify` on many samples (issue 15 item 5: 100,000 samples within 60 s and 2 GB).

    python benchmarks/identify_scale.py [--n 1000 10000 100000] [--device position|pose]
                                        [--out benchmarks/results/identify_scale.json]

Each size runs in its own process (a fresh interpreter: the peak RSS of one size is not the high-water mark of
an earlier, larger one). Data: the Stanford arm (seed 001 Table 1) with 1 mm / 2 mrad / 1e-3 gain errors,
random joint values, a laser tracker 4 m away and rotated 150 degrees (mm-level marker offset unknown),
0.02 mm noise per axis. The first `identify` call compiles; the second is timed ("run"). Peak RSS is the
process high-water mark (resource.getrusage), compilation included.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HERE = os.path.dirname(os.path.abspath(__file__))


def one_size(n: int, kind: str) -> dict:
    """Simulate n samples, identify twice (compile, then run); times, accuracy and peak memory."""
    import numpy as np
    from gap_scale import far_frame

    import jaxcal as jc

    rb = jc.robots.get("stanford")
    a_true = jc.perturb(rb, {"length": 1e-3, "angle": 2e-3, "gain": 1e-3}, seed=1)
    dev = jc.make_device(kind)
    q = jc.random_configurations(rb, n, seed=2)
    noise = {"position": 2e-5, "orientation": 2e-5}
    data = jc.simulate(rb, a_true, q, dev, noise=noise, device_params=far_frame(dev), seed=3)
    test = jc.simulate(rb, a_true, jc.random_configurations(rb, 500, seed=4), dev, noise=noise, device_params=far_frame(dev),
                       seed=5)
    t = time.perf_counter()
    first = jc.identify(rb, data, sigma_position=2e-5, sigma_orientation=2e-5)
    t_first = time.perf_counter() - t
    t = time.perf_counter()
    fit = jc.identify(rb, data, sigma_position=2e-5, sigma_orientation=2e-5)
    t_run = time.perf_counter() - t
    return dict(n=n, device=kind, first_s=t_first, compile_s=first.timings["compile_s"], run_s=t_run,
                iterations=fit.iterations, converged=bool(fit.converged), healthy=bool(fit.health.ok),
                rms_after_mm=fit.rms_after, heldout_mm=fit.rms_on(test), noise_floor_mm=float(np.sqrt(3) * 2e-2),
                peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[1000, 10_000, 100_000])
    ap.add_argument("--device", default="position", choices=("position", "pose"))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "identify_scale.json"))
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child process: one size, JSON on stdout
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one_size(args.one, args.device)))
        return
    rows = []
    for n in args.n:
        out = subprocess.run([sys.executable, __file__, "--one", str(n), "--device", args.device], capture_output=True, text=True,
                             cwd=HERE, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(f"N={r['n']:>7} {r['device']}: first call {r['first_s']:.1f} s (solver compile {r['compile_s']:.1f} s), "
              f"run {r['run_s']:.2f} s, {r['iterations']} LM steps, converged {r['converged']}, healthy {r['healthy']}, "
              f"RMS {r['rms_after_mm']:.4f} mm, held-out {r['heldout_mm']:.4f} mm (floor {r['noise_floor_mm']:.4f}), "
              f"peak RSS {r['peak_rss_mb']:.0f} MB", flush=True)
    from jaxcal.report import write_text_atomic

    load = os.getloadavg()
    write_text_atomic(args.out, json.dumps({"load_average": load, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
