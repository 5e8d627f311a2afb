"""The segment-batch job's options and its config (:mod:`pipelines.inference.segment_batch` is the job): light on
purpose, neither torch nor zarr nor Ray, so that ``radarseg segment-batch --help`` and a wrong option answer at once."""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from models.runtime import Runtime
from pipelines.datasets.sharded_options import SHARD_FRAMES, add_execution_arguments
from pipelines.datasets.sources import SourceKind, add_source_arguments, source_from_args
from pipelines.jobs import always, cap, field_defaults, smoke
from pipelines.runtime_option import add_runtime_option, runtime_of
from radar.centres import MAX_OBJECTS, SCORE_THRESHOLD

SOURCE_KINDS = (SourceKind.STORE, SourceKind.RECORDING)


@dataclass(frozen=True)
class SegmentBatchConfig:
    """Arguments of the job, as given."""

    source: str  # "store:STORE.zarr" or "recording:DIR"
    detector: str
    segmenter: str
    out: str
    split: str | None = None  # store only: train, val, test; None = every valid frame
    limit: int | None = smoke(None, cap(4, fill=True))  # the first LIMIT selected frames only (smoke tests)
    score_threshold: float = SCORE_THRESHOLD
    max_objects: int = MAX_OBJECTS
    address: str | None = None
    workers: int | None = None  # segmenter actors; None = the cluster's CPUs
    cpus_per_worker: float = 1.0
    torch_threads: int = 1  # per actor: one core each, so actors scale instead of fighting over cores
    shard_frames: int = smoke(SHARD_FRAMES, cap(2))
    progress: bool = True
    in_process: bool = smoke(False, always(True))  # every shard in this process (one ShardSegmenter), no Ray
    runtime: str = "torch"  # what runs the pair (models.runtime.RUNTIMES)

    def __post_init__(self) -> None:
        Runtime.parse(self.runtime)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The job's arguments (shared by ``python -m pipelines.inference.segment_batch`` and ``radarseg
    segment-batch``)."""
    defaults = field_defaults(SegmentBatchConfig)
    add_source_arguments(parser, SOURCE_KINDS)
    parser.add_argument("--detector", required=True, help="detector checkpoint")
    parser.add_argument("--segmenter", required=True, help="segmenter checkpoint")
    parser.add_argument("--out", required=True, help="predictions store path (shared by all Ray nodes)")
    parser.add_argument("--split", choices=["train", "val", "test"],
                        help="store source: the split to segment (default: every valid frame)")
    parser.add_argument("--limit", type=int, help="segment only the first LIMIT selected frames (smoke runs)")
    parser.add_argument("--score-threshold", type=float, default=SCORE_THRESHOLD, help="detector score threshold")
    parser.add_argument("--max-objects", type=int, default=MAX_OBJECTS,
                        help="detections per frame and width of the object table")
    parser.add_argument("--workers", type=int, help="segmenter actors, each loading the model once "
                                                    "(default: the cluster's CPUs / --cpus-per-worker)")
    parser.add_argument("--cpus-per-worker", type=float, default=defaults.cpus_per_worker,
                        help="CPUs reserved per actor")
    parser.add_argument("--torch-threads", type=int, default=defaults.torch_threads, help="torch threads per actor")
    add_runtime_option(parser, "what runs the pair in each actor: torch (default), torch-int8 (the segmenter in the "
                               "int8 sparse kernels, calibrated in each actor on simulated frames of the preset), onnx "
                               "or onnx-int8 (exported once into each node's $RADARSEG_ONNX_CACHE, default "
                               "~/.cache/radarseg/onnx)")
    add_execution_arguments(parser)


def config_from_args(args: argparse.Namespace) -> SegmentBatchConfig:
    return SegmentBatchConfig(
        source=source_from_args(args, SOURCE_KINDS), detector=str(Path(args.detector).expanduser().absolute()),
        segmenter=str(Path(args.segmenter).expanduser().absolute()), out=str(Path(args.out).expanduser().absolute()),
        split=args.split, limit=args.limit, score_threshold=args.score_threshold, max_objects=args.max_objects,
        address=args.address, workers=args.workers, cpus_per_worker=args.cpus_per_worker,
        torch_threads=args.torch_threads, shard_frames=args.shard_frames, progress=args.progress,
        in_process=args.in_process, runtime=runtime_of(args),
    )
