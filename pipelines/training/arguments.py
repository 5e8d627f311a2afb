"""The command-line options every trainer shares (``radarseg train`` and ``radarseg train-baseline``), and the
config fields they set."""

from __future__ import annotations

import argparse
import json
from typing import Any

from pipelines.jobs import field_defaults
from pipelines.renamed_options import add_renamed
from pipelines.training.config import OPTIMIZERS, RECIPE_NAMES, TrainConfig


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = field_defaults(TrainConfig)
    parser.add_argument("--store", required=True, help="preprocessed store (zarr)")
    parser.add_argument("--out", required=True, help="run directory (keep it outside the repository, or under "
                                                     "runs/, which git and ray job submit ignore)")
    parser.add_argument("--recipe", choices=RECIPE_NAMES, default=defaults.recipe,
                        help="training recipe (hyperparameters): quick (2-core CPU), crops (paper-size radars on a "
                             "CPU: the detector on windows) or paper (GPUs)")
    add_renamed(parser, "--profile", "--recipe", " (a profile is a radar's; training takes a recipe)")
    parser.add_argument("--model-config", type=json.loads, help="builder keyword arguments as JSON")
    parser.add_argument("--epochs", type=int, help="epochs (default: the recipe's)")
    parser.add_argument("--batch-size", type=int, help="frames per step, >= 2 (default: the recipe's)")
    parser.add_argument("--lr", type=float, help="learning rate (default: the recipe's)")
    parser.add_argument("--optimizer", choices=OPTIMIZERS,
                        help="instead of the recipe's (detector and baselines Adam, segmenter SGD), e.g. Adam for "
                             "sparsity training")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="seed of initialisation and shuffling")
    parser.add_argument("--device", default=defaults.device, help="auto (CUDA when present), cpu, cuda, cuda:N")
    parser.add_argument("--train-split", default=defaults.train_split, help="store split trained on")
    parser.add_argument("--val-split", default=defaults.val_split,
                        help="'none' to skip validation (model.pt = last epoch)")
    parser.add_argument("--max-steps", type=int, help="stop after this many optimiser steps (smoke runs)")
    parser.add_argument("--max-minutes", type=float,
                        help="stop after this many minutes of training (validation included; equal budgets)")
    parser.add_argument("--threads", type=int, default=defaults.threads, help="torch threads (0: torch's default)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    parser.add_argument("--workers", type=int, default=defaults.workers, help="DataLoader worker processes")
    parser.add_argument("--ray-workers", type=int, default=defaults.ray_workers,
                        help="data-parallel Ray Train workers (0: no Ray)")
    parser.add_argument("--address", help="Ray address for --ray-workers (default: embedded local Ray)")
    parser.add_argument("--slim-lambda", type=float, nargs="?", const=1e-4, default=defaults.slim_lambda,
                        help="network slimming: L1 weight on every BatchNorm scale (1e-4 when given alone)")
    parser.add_argument("--init", help="start from this checkpoint's architecture and weights (e.g. a pruned one)")
    parser.add_argument("--val-frames", type=int,
                        help="validation frames scored per epoch, evenly spread (default: the recipe's; 0 = all)")
    parser.add_argument("--curve-every", type=int, default=defaults.curve_every, metavar="STEPS",
                        help="learning curve: validate before the first step, every STEPS steps and at each epoch's "
                             "end into RUN/curve.jsonl, against training CPU seconds (0: off)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def common_config(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`~pipelines.training.config.TrainConfig` fields of :func:`add_common_arguments`' options."""
    return dict(store=args.store, out=args.out, recipe=args.recipe, model_config=args.model_config,
                epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, optimizer=args.optimizer, seed=args.seed,
                device=args.device, train_split=args.train_split,
                val_split=None if args.val_split.lower() == "none" else args.val_split,
                max_steps=args.max_steps, max_minutes=args.max_minutes, threads=args.threads, resume=args.resume,
                workers=args.workers, ray_workers=args.ray_workers, address=args.address,
                progress=not args.no_progress, slim_lambda=args.slim_lambda, init=args.init,
                val_frames=args.val_frames, curve_every=args.curve_every)


def format_training(result: dict[str, Any]) -> str:
    """What a trainer prints for people: the run, its checkpoint and the last epoch's figures (``--json``: all of
    ``result`` as one JSON line); for ``train export``, the copy and its size."""
    if "class_offsets" in result:
        record = result["class_offsets"]
        views = {when: " / ".join(f"{100 * record[when][view]['mIoU']:.2f}" for view in ("RA", "RD"))
                 for when in ("before", "after")}
        offsets = ", ".join(f"{name} {value:+.3f}" for name, value in record["offsets"].items())
        return (f"{result['checkpoint']}: offsets {offsets} on {record['frames']} frames; RA / RD mIoU "
                f"{views['before']} -> {views['after']}")
    if "class_gains" in result:
        classes = result["class_gains"]["classes"]
        return f"{result['checkpoint']}: " + ", ".join(
            f"{name} threshold {c['threshold']:.3f} (gain {c['gain']:.2f}; F1 {c['f1']:.3f}, precision "
            f"{c['precision']:.3f}, recall {c['recall']:.3f} of {c['truths']})" for name, c in classes.items())
    if "run" not in result:
        return f"{result['checkpoint']}: {result['bytes'] / 1e6:.2f} MB"
    metrics = result.get("metrics") or {}
    figures = ", ".join(f"{key} {value:.4g}" for key, value in metrics.items()
                        if isinstance(value, float) and (key.startswith("val_") or key == "train_total"))
    return (f"run {result['run']}: {metrics.get('epoch', 0)} epochs in {result['seconds']:.0f} s; best epoch in "
            f"{result['checkpoint']}\nlast epoch: {figures or 'no figures'}")
