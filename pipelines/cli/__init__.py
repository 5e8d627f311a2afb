"""The ``radarseg`` command line, one style for every command: each is a thin shell over a function of pipelines/.

The jobs (:data:`JOBS`: preprocess, segment-batch, train, train-baseline, evaluate, compare, slim-sweep) follow the
job contract (:mod:`pipelines.jobs`): a config dataclass, options declared in a light module, ``python -m`` and Ray
alike. Every other command lives in the module of its group, which declares its parsers in ``add_commands(sub)``
beside the functions that run them:

- :mod:`pipelines.cli.data_commands`: simulate, prune, store info;
- :mod:`pipelines.cli.frame_commands`: segment, export onnx|recording, process-adc;
- :mod:`pipelines.cli.radar_commands`: radar show|tune-growing|from-ti;
- :mod:`pipelines.cli.capture_commands`: capture (a DCA1000's UDP stream) and capture replay;
- :mod:`pipelines.cli.model_commands`: upload-check, models summary;
- :mod:`pipelines.cli.service_commands`: serve, demo.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import NamedTuple

from pipelines.cli import (
    capture_commands,
    data_commands,
    frame_commands,
    model_commands,
    radar_commands,
    service_commands,
)
from pipelines.jobs import USER_ERRORS, report_error, run_job, with_defaults_shown


class Job(NamedTuple):
    """A job command (:mod:`pipelines.jobs`' contract): the module that runs it, its one-line help, and the module
    that declares its options, which loads neither torch nor zarr (``--help`` answers at once)."""

    module: str
    help: str
    options: str


# The jobs: command -> Job. A job module loads only when its command runs, after its options have parsed.
JOBS: dict[str, Job] = {
    "preprocess": Job("pipelines.datasets.preprocess", "Ray job: cubes into the zarr store of inputs and targets",
                      "pipelines.datasets.preprocess_options"),
    "segment-batch": Job("pipelines.inference.segment_batch", "Ray job: segment a store split or a recording into a "
                                                               "predictions store",
                         "pipelines.inference.segment_batch_options"),
    "train": Job("pipelines.training.train", "train the detector or the segmenter from a store, or export a checkpoint",
                 "pipelines.training.train"),
    "train-baseline": Job("pipelines.training.train_baselines",
                          "train a 2-D baseline (unet, tmvanet, smvanet) from a store",
                          "pipelines.training.train_baselines"),
    "evaluate": Job("pipelines.evaluation.evaluate",
                    "evaluate both stages on a split of a store: metrics.json, report.md, pictures",
                    "pipelines.evaluation.evaluate_options"),
    "compare": Job("pipelines.evaluation.compare", "ERASE-Net and the 2-D baselines on the same frames: compare.json, "
                                                   "compare.md, compare_frames.png",
                   "pipelines.evaluation.compare_options"),
    "slim-sweep": Job("pipelines.training.slim_sweep", "compression sweep: prune (and fine-tune) at several ratios, "
                                                       "reports/slimming.md and .png",
                      "pipelines.training.slim_sweep_options"),
}


def job_parser_of(command: str) -> argparse.ArgumentParser:
    """The parser that reads a job command's options (``radarseg train ...``): the one its options module declares
    (:mod:`pipelines.jobs`). The top-level parser only names the jobs; the reference pages and their test walk
    these for every option."""
    from pipelines.jobs import OPTIONS, job_module, job_parser

    return job_parser(job_module(JOBS[command].options, OPTIONS), prog=f"radarseg {command}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="radarseg", description="ERASE-Net radar semantic segmentation")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--version", action="version", version=f"radarseg {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    data_commands.add_commands(sub)
    for name, job in JOBS.items():  # parsed by the job's own parser (see main)
        sub.add_parser(name, add_help=False, help=job.help)
    frame_commands.add_commands(sub)
    radar_commands.add_commands(sub)
    capture_commands.add_commands(sub)
    model_commands.add_commands(sub)
    service_commands.add_commands(sub)
    return with_defaults_shown(parser)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("radarseg")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def _command_index(argv: list[str]) -> int | None:
    """Position of the command in ``argv`` (the first word that is not a top-level option)."""
    return next((i for i, word in enumerate(argv) if not word.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    at = _command_index(argv)
    command = argv[at] if at is not None else None
    verbose = "-v" in argv[:at] or "--verbose" in argv[:at]
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if command in JOBS:  # a job: its own parser reads the rest (pipelines.jobs)
        try:
            job = JOBS[command]
            _, summary = run_job(job.module, argv[at + 1:], prog=f"radarseg {command}", options=job.options)
        except USER_ERRORS as exc:
            return report_error(f"radarseg {command}", exc)
        print(summary)
        return 0
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except USER_ERRORS as exc:
        return report_error(f"radarseg {args.command}", exc)
