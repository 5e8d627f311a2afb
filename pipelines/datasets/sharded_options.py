"""What every sharded job (preprocess, segment-batch) is told about how it runs: where (Ray or this process), in
shards of how many frames, with or without a progress bar. Light on purpose: the jobs' options import it, and they
load neither Ray nor zarr, so ``radarseg preprocess --help`` answers at once."""

from __future__ import annotations

import argparse

SHARD_FRAMES = 8  # frames per shard of every sharded store (input and predictions), unless a job is told otherwise


def add_execution_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments every sharded job takes (how many shards in flight is the job's own: tasks or actors)."""
    parser.add_argument("--address", help="Ray address (default: embedded local Ray, or the job's cluster)")
    parser.add_argument("--shard-frames", type=int, default=SHARD_FRAMES, help="frames per shard")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    parser.add_argument("--in-process", action="store_true",
                        help="run every shard in this process, without Ray (smoke runs and tests)")
