"""The slim-sweep job's options and its config (:mod:`pipelines.training.slim_sweep` is the job): light on purpose,
no torch, so that ``radarseg slim-sweep --help`` and a wrong option answer at once."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from models.capabilities import Stage
from pipelines.jobs import always, cap, field_defaults, first, smoke

PAPER_RATIOS = (0.1, 0.3, 0.4, 0.6, 0.7)
# The sweep's checkpoint arguments and the stage (models.capabilities) each one's model must declare:
# scoring, fine-tuning and the learning rate follow the stage.
SLIMMED: dict[str, Stage] = {"detector": Stage.DETECTOR, "minkunet": Stage.SEGMENTER, "spvcnn": Stage.SEGMENTER,
                          "smvanet": Stage.BASELINE}


@dataclass(frozen=True)
class SweepConfig:
    """A sweep. Checkpoints left as None are skipped (the segmenters need the detector)."""

    store: str
    out: str = "reports"
    work: str = "out/slim-sweep"
    detector: str | None = None
    minkunet: str | None = None
    spvcnn: str | None = None
    smvanet: str | None = None
    ratios: tuple[float, ...] = smoke(PAPER_RATIOS, first)
    split: str = "test"
    max_frames: int = smoke(0, cap(2, fill=True))  # frames scored per model and ratio (0 = the whole split)
    finetune_steps: int = smoke(0, cap(1))  # 0 = prune only
    finetune_steps_baseline: int | None = smoke(None, cap(1))  # SMVA-Net's if its steps cost too much (None: the same)
    lr_erasenet: float = 1e-3
    lr_baseline: float = 1e-5
    batch_size: int = smoke(4, cap(2, fill=True))
    threads: int = smoke(1, always(1))
    seed: int = 0
    notes: str = ""  # how the input checkpoints were made (printed in the report)

    def __post_init__(self) -> None:
        if any(not 0 <= r < 1 for r in self.ratios):
            raise ValueError(f"ratios must lie in [0, 1), got {self.ratios}")
        if (self.minkunet or self.spvcnn) and not self.detector:
            raise ValueError("the ERASE-Net segmenters are scored end to end: give --detector too")
        if self.max_frames < 0 or self.finetune_steps < 0 or (self.finetune_steps_baseline or 0) < 0:
            raise ValueError("max_frames and finetune steps must be >= 0")

    def steps(self, kind: str) -> int:
        """Fine-tuning steps after pruning for the checkpoint given as ``--<kind>``."""
        if SLIMMED[kind] is Stage.BASELINE and self.finetune_steps_baseline is not None:
            return self.finetune_steps_baseline
        return self.finetune_steps


# --------------------------------------------------------------------------- scoring


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = field_defaults(SweepConfig)
    parser.add_argument("--store", required=True, help="preprocessed store (zarr) to score (and fine-tune) on")
    parser.add_argument("--out", default=defaults.out, help="where slimming.md/.png/.json go")
    parser.add_argument("--work", default=defaults.work, help="pruned checkpoints and fine-tune runs")
    for kind in SLIMMED:
        parser.add_argument(f"--{kind}", help=f"{kind} checkpoint (trained with --slim-lambda, ideally)")
    parser.add_argument("--ratios", type=float, nargs="+", default=list(PAPER_RATIOS),
                        help="compression ratios (fraction of BatchNorm channels removed)")
    parser.add_argument("--split", default=defaults.split, help="store split scored")
    parser.add_argument("--max-frames", type=int, default=defaults.max_frames,
                        help="frames scored per model and ratio (0: all)")
    parser.add_argument("--finetune-steps", type=int, default=defaults.finetune_steps,
                        help="optimiser steps after pruning (0: none)")
    parser.add_argument("--finetune-steps-smvanet", type=int, help="SMVA-Net's fine-tuning steps (default: the same)")
    parser.add_argument("--lr-erasenet", type=float, default=defaults.lr_erasenet,
                        help="fine-tuning lr of the detector and segmenters")
    parser.add_argument("--lr-baseline", type=float, default=defaults.lr_baseline,
                        help="fine-tuning lr of the baselines")
    parser.add_argument("--batch-size", type=int, default=defaults.batch_size, help="fine-tuning batch size")
    parser.add_argument("--threads", type=int, default=defaults.threads, help="torch threads")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="seed of fine-tuning")
    parser.add_argument("--notes-file", help="markdown file saying how the checkpoints were made (goes in the report)")


def config_from_args(args: argparse.Namespace) -> SweepConfig:
    return SweepConfig(store=args.store, out=args.out, work=args.work, detector=args.detector,
                       minkunet=args.minkunet, spvcnn=args.spvcnn, smvanet=args.smvanet, ratios=tuple(args.ratios),
                       split=args.split, max_frames=args.max_frames, finetune_steps=args.finetune_steps,
                       finetune_steps_baseline=args.finetune_steps_smvanet,
                       lr_erasenet=args.lr_erasenet, lr_baseline=args.lr_baseline, batch_size=args.batch_size,
                       threads=args.threads, seed=args.seed,
                       notes=Path(args.notes_file).read_text().strip() if args.notes_file else "")
