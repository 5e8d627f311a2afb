"""Training of the 2-D baselines (U-Net per view, TMVA-Net, SMVA-Net; docs/design.md section 9) with the same loop
as ERASE-Net (:mod:`pipelines.training`; the stage is :mod:`pipelines.training.baselines`)::

    radarseg train-baseline tmvanet --store STORE.zarr --out runs/tmva [--recipe quick|paper]
    radarseg train-baseline unet --view ra --store STORE.zarr --out runs/unet-ra [--resume]
    python -m pipelines.training.train_baselines ...                       # the same arguments
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from pipelines.jobs import run_module
from pipelines.training.arguments import add_common_arguments, common_config, format_training
from pipelines.training.config import TrainConfig

MODELS = ("unet", "tmvanet", "smvanet", "unet_tiny", "tmvanet_tiny", "smvanet_tiny")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", choices=MODELS, help="baseline architecture")
    parser.add_argument("--view", choices=("ra", "rd"), help="one-view models (U-Net): the view it segments")
    add_common_arguments(parser)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(stage="baseline", model=args.model, view=args.view, **common_config(args))


def main(cfg: TrainConfig) -> dict[str, Any]:
    from pipelines.training.loop import train  # torch and zarr load with the work, not with the options (--help)

    return train(cfg)


format_result = format_training

if __name__ == "__main__":
    sys.exit(run_module("pipelines.training.train_baselines"))
