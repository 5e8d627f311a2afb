"""The interface between the training loop and a stage: what a stage builds, reads, optimises and scores.

A task never runs the loop; :func:`pipelines.training.loop.train_loop` owns resume, budget, checkpoints,
metrics lines, the slimming penalty and Ray Train for every task alike.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import Dataset

from models.registry import create_model
from pipelines.datasets.store_info import StoreInfo
from pipelines.training.config import Hyper, TrainConfig
from radar.errors import UserError


def unwrap(model: nn.Module) -> nn.Module:
    """The model inside a DistributedDataParallel wrapper (or the model itself)."""
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


class Task:
    """One stage. Subclasses set ``stage`` and ``monitor`` and implement the data, loss and validation."""

    stage: str = ""
    monitor: str = ""  # validation metric that picks model.pt (higher is better)

    def __init__(self, cfg: TrainConfig, hyper: Hyper, store: StoreInfo, run_dir: Path):
        self.cfg = cfg
        self.hyper = hyper
        self.store = store
        self.run_dir = run_dir

    def model_config(self) -> dict[str, Any]:
        """The registered builder's keyword arguments (what the checkpoint stores)."""
        config = {"preset": self.store.profile.name, **self.hyper.model_config}
        if self.cfg.view is not None:
            config["view"] = self.cfg.view
        return config

    def build_model(self) -> nn.Module:
        """The model for the store's radar (its profile, so that a radar described by a file builds too)."""
        try:
            return create_model(self.hyper.model, **{**self.model_config(), "preset": self.store.profile})
        except TypeError as exc:  # an argument the builder does not take: the user's --model-config
            raise UserError(f"model {self.hyper.model!r} cannot be built with {self.model_config()}: {exc} "
                             "(check --model-config)") from None

    def prepare(self, model: nn.Module, rank: int) -> None:
        """One-off work before training (rank 0 writes files; every rank must end up with the same state)."""

    def train_dataset(self) -> Dataset:
        raise NotImplementedError

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        raise NotImplementedError

    def batch_size_of(self, batch: dict[str, Any]) -> int:
        """Samples in a collated batch (for the frames/s figure)."""
        return self.hyper.batch_size

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        """Named losses of one batch; ``total`` is minimised."""
        raise NotImplementedError

    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        """``val_*`` figures on the validation split (empty when there is none)."""
        return {}

    def normalisation(self) -> dict[str, Any]:
        """The input scaling the checkpoint carries (the store's statistics by default)."""
        return dict(self.store.normalisation)

    def extra(self) -> dict[str, Any]:
        """Stage facts the checkpoint carries beside the weights."""
        return {}
