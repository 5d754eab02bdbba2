"""Command line: `jaxcal demo`, `jaxcal --help`."""

from __future__ import annotations

import argparse
import sys


def _demo(args) -> int:
    from jaxcal.demo import run

    run(args.out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxcal", description="Differentiable robot calibration in JAX.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    d = sub.add_parser("demo", help="calibrate MRR-1 and the Stanford arm on simulated data, print a report, write plots")
    d.add_argument("--out", default="demo-output", help="folder for the report and plots (default: demo-output)")
    d.set_defaults(func=_demo)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
