"""``--runtime``, the one option every command that runs ERASE-Net takes (:class:`models.runtime.Runtime`'s names),
and the former ``--engine`` / ``--precision`` pair, still accepted with a note that names the new option."""

from __future__ import annotations

import argparse
import sys

from models.runtime import PRECISIONS, RUNTIMES, Runtime
from radar.errors import UserError

HELP = ("what runs the pair: torch (default; PyTorch and the compiled sparse kernels), torch-int8 (the segmenter in "
        "the int8 sparse kernels, calibrated at load), onnx (the exported graphs in onnxruntime, exported on first use "
        "into $RADARSEG_ONNX_CACHE, default ~/.cache/radarseg/onnx) or onnx-int8 (those graphs statically quantised)")


def add_runtime_option(parser: argparse.ArgumentParser, help: str = HELP) -> None:  # noqa: A002 (argparse's name)
    parser.add_argument("--runtime", choices=RUNTIMES, help=help)
    parser.add_argument("--engine", choices=("torch", "onnx", "onnx-int8"), help=argparse.SUPPRESS)
    parser.add_argument("--precision", choices=PRECISIONS, help=argparse.SUPPRESS)


def runtime_of(args: argparse.Namespace) -> str:
    """The runtime's name from ``--runtime``, or from the former pair (with a note on stderr); torch by default.

    Raises:
        UserError: ``--runtime`` and the former pair name different runtimes.
    """
    if args.engine is None and args.precision is None:
        return args.runtime or "torch"
    former = Runtime.from_engine(args.engine or "torch", args.precision or "float")
    if args.runtime is not None and Runtime.parse(args.runtime) != former:
        raise UserError(f"--runtime {args.runtime} and the former --engine/--precision ({former.name}) disagree: "
                        f"give --runtime alone")
    print(f"note: --engine and --precision are now one option: --runtime {former.name}", file=sys.stderr)
    return former.name
