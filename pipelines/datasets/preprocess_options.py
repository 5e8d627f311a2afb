"""The preprocess job's options and its config (:mod:`pipelines.datasets.preprocess` is the job): light on purpose,
neither torch nor zarr nor Ray, so that ``radarseg preprocess --help`` and a wrong option answer at once."""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from pipelines.datasets.sharded_options import SHARD_FRAMES, add_execution_arguments
from pipelines.datasets.sources import SourceKind, add_source_arguments, source_from_args
from pipelines.jobs import always, cap, field_defaults, smoke
from pipelines.radar_option import RADAR_HELP, add_radar_option
from radar.centres import MAX_OBJECTS

SOURCE_KINDS = (SourceKind.SIM, SourceKind.RECORDING, SourceKind.ADC_RECORDING, SourceKind.CARRADA)


@dataclass(frozen=True)
class PreprocessConfig:
    """Arguments of the job, as given (None = the source's default, resolved by :func:`plan_job`)."""

    source: str  # "sim", "recording:DIR" or "carrada:ROOT"
    out: str  # store path (a directory ending in .zarr by convention)
    preset: str | None = None  # sim only (default small)
    sequences: int | None = smoke(None, cap(4))  # sim only (default 2)
    frames: int | None = smoke(None, cap(6))  # sim only: frames per sequence (default 8)
    seed: int = 0  # sim only
    split_fractions: tuple[float, float, float] | None = None  # train, val, test by sequence
    address: str | None = None  # Ray address; None = embedded local Ray (or RAY_ADDRESS under a job)
    tasks: int | None = None  # shard tasks in flight; None = the cluster's CPUs
    shard_frames: int = smoke(SHARD_FRAMES, cap(2))  # TMVA-Net needs 5 frames
    max_objects: int = MAX_OBJECTS
    progress: bool = True
    in_process: bool = smoke(False, always(True))  # every shard in this process, no Ray

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["split_fractions"] = None if self.split_fractions is None else list(self.split_fractions)
        return data


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The job's arguments (shared by ``python -m pipelines.datasets.preprocess`` and ``radarseg preprocess``)."""
    defaults = field_defaults(PreprocessConfig)
    add_source_arguments(parser, SOURCE_KINDS)
    parser.add_argument("--out", required=True, help="store path, e.g. data/small.zarr (shared by all Ray nodes)")
    add_radar_option(parser, former=True, help=f"sim: {RADAR_HELP} (default small)")
    parser.add_argument("--sequences", type=int, help="sim: number of sequences (default 2)")
    parser.add_argument("--frames", type=int, help="sim: frames per sequence (default 8)")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="sim: scene seed")
    parser.add_argument("--split-fractions", type=float, nargs=3, metavar=("TRAIN", "VAL", "TEST"),
                        help="split by sequence in name order (default 0.7 0.15 0.15; CARRADA: its split file)")
    parser.add_argument("--tasks", type=int, help="shard tasks in flight (default: the cluster's CPUs)")
    parser.add_argument("--max-objects", type=int, default=MAX_OBJECTS, help="width of the object table")
    add_execution_arguments(parser)


def config_from_args(args: argparse.Namespace) -> PreprocessConfig:
    return PreprocessConfig(
        source=source_from_args(args, SOURCE_KINDS), out=str(Path(args.out).expanduser().absolute()),
        preset=args.profile, sequences=args.sequences, frames=args.frames, seed=args.seed,
        split_fractions=None if args.split_fractions is None else tuple(args.split_fractions),
        address=args.address, tasks=args.tasks, shard_frames=args.shard_frames, max_objects=args.max_objects,
        progress=args.progress, in_process=args.in_process,
    )
