"""The ``radarseg`` command line: each command is a thin shell over a function of pipelines/."""

from __future__ import annotations

import argparse
import logging
import sys

from radar.io.errors import DataError
from radar.profiles import PRESETS


def _cmd_simulate(args: argparse.Namespace) -> int:
    from pipelines.record import simulate_recording

    out = simulate_recording(preset=args.preset, sequences=args.sequences, frames=args.frames,
                             seed=args.seed, out=args.out)
    print(f"recording written to {out}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from pipelines.demo import run_demo

    result = run_demo(args.out)
    print(f"simulated {result['frames']} frames into {result['recording']}")
    print("RA/RD pictures with labels:")
    for path in result["pictures"]:
        print(f"  {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="radarseg", description="ERASE-Net radar semantic segmentation")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="simulate a labelled recording with the FMCW scene simulator")
    sim.add_argument("--preset", choices=sorted(PRESETS), default="small")
    sim.add_argument("--sequences", type=int, default=2)
    sim.add_argument("--frames", type=int, default=8, help="frames per sequence")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--out", required=True, help="output directory (must not hold a recording yet)")
    sim.set_defaults(func=_cmd_simulate)

    demo = sub.add_parser("demo", help="run the end-to-end demo on embedded defaults")
    demo.add_argument("--out", default="out/demo")
    demo.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (DataError, ValueError, FileExistsError) as exc:
        print(f"radarseg {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
