"""Training of both ERASE-Net stages from the preprocessed store (docs/design.md sections 5 and 7), and the export
of a shippable checkpoint::

    radarseg train detector  --store STORE.zarr --out runs/det [--recipe quick|paper] [--resume]
    radarseg train segmenter --store STORE.zarr --out runs/seg --jitter-from runs/det/model.pt
    radarseg train export RUN/model.pt checkpoints/detector.pt   # float16 weights only
    radarseg train class-gains RUN/model.pt TUNED.pt --store STORE.zarr   # a threshold per class (heatmap per class)
    radarseg train class-offsets SEG.pt TUNED.pt --store STORE.zarr --detector DET.pt   # the segmenter's logit offsets
    python -m pipelines.training.train ...                                # the same arguments

The loop, the tasks and the recipes live in :mod:`pipelines.training`; this module is the job
(:mod:`pipelines.jobs`): options, config, ``main(cfg) -> dict``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Any

from models.capabilities import ERASENET_STAGES, Stage
from pipelines.jobs import always, cap, field_defaults, run_module, smoke
from pipelines.training.arguments import add_common_arguments, common_config, format_training
from pipelines.training.config import TrainConfig
from radar.errors import UserError


@dataclass(frozen=True)
class CheckpointCopy:
    """A command that writes a copy of the checkpoint ``source`` to ``target``; what the copy changes is the
    subclass's."""

    source: str
    target: str


@dataclass(frozen=True)
class ExportConfig(CheckpointCopy):
    """``radarseg train export SOURCE TARGET``: a shippable copy of a checkpoint."""

    float16: bool = True


@dataclass(frozen=True)
class ClassGainsConfig(CheckpointCopy):
    """``radarseg train class-gains SOURCE TARGET --store STORE``: a threshold per class, chosen on a split."""

    store: str
    split: str = "val"
    frames: int = smoke(0, cap(6))


@dataclass(frozen=True)
class ClassOffsetsConfig(CheckpointCopy):
    """``radarseg train class-offsets SOURCE TARGET --store STORE --detector DET``: the segmenter's logit offsets."""

    stores: tuple[str, ...]
    detector: str
    split: str | None = "val"
    max_frames: int = smoke(0, cap(2, fill=True))  # of each store's split, evenly spread; 0: all
    progress: bool = True
    threads: int = smoke(0, always(1))  # torch intra-op threads (0: torch's default)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    stages = parser.add_subparsers(dest="stage", required=True,
                                   metavar="{detector,segmenter,export,class-gains,class-offsets}")
    for stage in ERASENET_STAGES:
        sub = stages.add_parser(stage, help=f"train the {stage} from a store")
        sub.add_argument("--model", help="registered model name (default: the recipe's)")
        add_common_arguments(sub)
        if stage is Stage.DETECTOR:
            sub.add_argument("--class-weights", type=float, nargs="+", metavar="W",
                             help="the centre loss's weight at each foreground class's centres, in the store's "
                                  "class order (e.g. 3 1 1: pedestrians' peaks count 3x; default: 1 each)")
            sub.add_argument("--crop", type=int, nargs=2, metavar=("RANGE", "ANGLE"),
                             help="train on range x angle windows of this many bins (multiples of 4; the whole "
                                  "Doppler axis), most around an object, some clutter only; validation stays on "
                                  "whole frames (default: the recipe's; the crops recipe: 64 128)")
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
    gains = stages.add_parser("class-gains", help="a detector with a heatmap per class: each class's threshold "
                                                  "(best F1 on a split), written into a copy of the checkpoint")
    gains.add_argument("source", help="detector checkpoint trained with --model-config '{\"heatmap_classes\": N}'")
    gains.add_argument("target", help="the copy to write, with the class gains")
    gains.add_argument("--store", required=True, help="preprocessed store whose split chooses the thresholds")
    gains_defaults = field_defaults(ClassGainsConfig)
    gains.add_argument("--split", default=gains_defaults.split, help="split of the store")
    gains.add_argument("--frames", type=int, default=gains_defaults.frames,
                       help="frames of the split, evenly spread (0: all)")
    offsets = stages.add_parser("class-offsets", help="a segmenter's offset per class on its logits (best mean RA/RD "
                                                      "mIoU on a store's frames from a detector's centres), written "
                                                      "into a copy of the checkpoint")
    offsets.add_argument("source", help="segmenter checkpoint")
    offsets.add_argument("target", help="the copy to write, the offsets in its classifier's bias")
    offsets.add_argument("--store", required=True, action="append", help="preprocessed store whose frames choose "
                                                                         "the offsets (repeat it for several)")
    offsets.add_argument("--detector", required=True, help="the detector whose seeds the segmenter is paired with")
    offsets_defaults = field_defaults(ClassOffsetsConfig)
    offsets.add_argument("--split", default=offsets_defaults.split, help="split of the store ('all': every frame)")
    offsets.add_argument("--frames", type=int, default=offsets_defaults.max_frames,
                         help="frames of the split, evenly spread (0: all)")
    offsets.add_argument("--threads", type=int, default=offsets_defaults.threads,
                         help="torch threads (0: torch's default)")
    offsets.add_argument("--no-progress", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> TrainConfig | ExportConfig | ClassGainsConfig | ClassOffsetsConfig:
    if args.stage == "export":
        return ExportConfig(args.source, args.target, float16=not args.float32)
    if args.stage in ("class-gains", "class-offsets") and args.frames < 0:
        raise UserError(f"--frames must be >= 0, got {args.frames}")
    if args.stage == "class-offsets" and args.threads < 0:
        raise UserError(f"--threads must be >= 0, got {args.threads}")
    if args.stage == "class-gains":
        return ClassGainsConfig(args.source, args.target, args.store, split=args.split, frames=args.frames)
    if args.stage == "class-offsets":
        return ClassOffsetsConfig(args.source, args.target, tuple(args.store), args.detector,
                                  split=None if args.split == "all" else args.split, max_frames=args.frames,
                                  progress=not args.no_progress, threads=args.threads)
    jitter_std = getattr(args, "jitter_std", None)
    return TrainConfig(stage=args.stage, model=args.model, jitter_from=getattr(args, "jitter_from", None),
                       jitter_std=tuple(jitter_std) if jitter_std else None,
                       lovasz_weight=getattr(args, "lovasz_weight", None),
                       class_weights=tuple(args.class_weights) if getattr(args, "class_weights", None) else None,
                       crop=tuple(args.crop) if getattr(args, "crop", None) else None,
                       **common_config(args))


def main(cfg: TrainConfig | ExportConfig | ClassGainsConfig | ClassOffsetsConfig) -> dict[str, Any]:
    """Train (the last epoch's metrics and where the run lives), export (the checkpoint and its size), or tune the
    class gains (the chosen thresholds) or the segmenter's class offsets. The work's modules (torch, zarr) load
    here, not with the options: ``radarseg train --help`` answers at once."""
    if isinstance(cfg, ClassOffsetsConfig):
        import torch

        from pipelines.training.class_offsets import write_class_offsets

        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        record = write_class_offsets(cfg.source, cfg.target, detector=cfg.detector, stores=list(cfg.stores),
                                     split=cfg.split, max_frames=cfg.max_frames, show_progress=cfg.progress)
        return {"checkpoint": cfg.target, "class_offsets": record}
    if isinstance(cfg, ClassGainsConfig):
        from pipelines.datasets.store_info import StoreInfo
        from pipelines.training.class_gains import write_class_gains

        record = write_class_gains(cfg.source, cfg.target, StoreInfo.read(cfg.store), split=cfg.split,
                                   max_frames=cfg.frames)
        return {"checkpoint": cfg.target, "class_gains": record}
    if isinstance(cfg, ExportConfig):
        from models.checkpoint import export_checkpoint

        target = export_checkpoint(cfg.source, cfg.target, float16=cfg.float16)
        return {"checkpoint": str(target), "bytes": target.stat().st_size}
    from pipelines.training.loop import train

    return train(cfg)


format_result = format_training


if __name__ == "__main__":
    sys.exit(run_module("pipelines.training.train"))
