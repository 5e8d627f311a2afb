"""Training of both ERASE-Net stages from the preprocessed store (docs/design.md sections 5 and 7), and the export
of a shippable checkpoint::

    radarseg train detector  --store STORE.zarr --out runs/det [--profile quick|paper] [--resume]
    radarseg train segmenter --store STORE.zarr --out runs/seg --jitter-from runs/det/model.pt
    radarseg train export RUN/model.pt checkpoints/detector.pt   # float16 weights only
    python -m pipelines.training.train ...                                # the same arguments

The loop, the tasks and the profiles live in :mod:`pipelines.training`; this module is the job
(:mod:`pipelines.jobs`): options, config, ``main(cfg) -> dict``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Any

from models.capabilities import ERASENET_STAGES, Stage
from models.checkpoint import export_checkpoint
from pipelines.jobs import run_module
from pipelines.training.arguments import add_common_arguments, common_config, format_training
from pipelines.training.config import TrainConfig
from pipelines.training.loop import train


@dataclass(frozen=True)
class ExportConfig:
    """``radarseg train export SOURCE TARGET``: a shippable copy of a checkpoint."""

    source: str
    target: str
    float16: bool = True


def add_arguments(parser: argparse.ArgumentParser) -> None:
    stages = parser.add_subparsers(dest="stage", required=True, metavar="{detector,segmenter,export}")
    for stage in ERASENET_STAGES:
        sub = stages.add_parser(stage, help=f"train the {stage} from a store")
        sub.add_argument("--model", help="registered model name (default: the profile's)")
        add_common_arguments(sub)
        if stage is Stage.DETECTOR:
            sub.add_argument("--class-weights", type=float, nargs="+", metavar="W",
                             help="the centre loss's weight at each foreground class's centres, in the store's "
                                  "class order (e.g. 3 1 1: pedestrians' peaks count 3x; default: 1 each)")
        if stage is Stage.SEGMENTER:
            sub.add_argument("--jitter-from", help="detector checkpoint whose errors (measured on the validation "
                                                   "split) jitter the training seeds")
            sub.add_argument("--jitter-std", type=float, nargs=3, metavar=("RANGE", "ANGLE", "DOPPLER"),
                             help="Gaussian seed errors in bins instead")
            sub.add_argument("--lovasz-weight", type=float,
                             help="add this weight x Lovasz-softmax to the weighted cross entropy (default 0: off)")
    export = stages.add_parser("export", help="a shippable copy of a checkpoint: weights only, float16")
    export.add_argument("source", help="training checkpoint (model.pt or last.pt)")
    export.add_argument("target", help="shippable copy to write (float16, no optimiser state)")
    export.add_argument("--float32", action="store_true", help="keep float32 weights (default float16)")


def config_from_args(args: argparse.Namespace) -> TrainConfig | ExportConfig:
    if args.stage == "export":
        return ExportConfig(args.source, args.target, float16=not args.float32)
    jitter_std = getattr(args, "jitter_std", None)
    return TrainConfig(stage=args.stage, model=args.model, jitter_from=getattr(args, "jitter_from", None),
                       jitter_std=tuple(jitter_std) if jitter_std else None,
                       lovasz_weight=getattr(args, "lovasz_weight", None),
                       class_weights=tuple(args.class_weights) if getattr(args, "class_weights", None) else None,
                       **common_config(args))


def main(cfg: TrainConfig | ExportConfig) -> dict[str, Any]:
    """Train (the last epoch's metrics and where the run lives), or export (the checkpoint and its size)."""
    if isinstance(cfg, ExportConfig):
        target = export_checkpoint(cfg.source, cfg.target, float16=cfg.float16)
        return {"checkpoint": str(target), "bytes": target.stat().st_size}
    return train(cfg)


format_result = format_training


if __name__ == "__main__":
    sys.exit(run_module("pipelines.training.train"))
