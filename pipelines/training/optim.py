"""What a training run builds from its resolved hyper-parameters (:class:`pipelines.training.config.Hyper`):
the device, the optimiser and the learning-rate schedule."""

from __future__ import annotations

import math

import torch

from pipelines.training.config import Hyper


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def make_optimizer(hyper: Hyper, params) -> torch.optim.Optimizer:
    """Adam, or SGD with Nesterov momentum. Adam drives unneeded BatchNorm scales to zero under the
    slimming penalty within a short run; SGD's steps of lr x lambda barely move them (reports/slimming.md)."""
    if hyper.optimizer == "adam":
        return torch.optim.Adam(params, lr=hyper.lr, weight_decay=hyper.weight_decay)
    return torch.optim.SGD(params, lr=hyper.lr, momentum=hyper.momentum, weight_decay=hyper.weight_decay,
                           nesterov=True)


def make_scheduler(hyper: Hyper, optimizer: torch.optim.Optimizer,
                   steps_per_epoch: int) -> torch.optim.lr_scheduler.LRScheduler:
    """``step``: stepped once per epoch (every ``step_every`` epochs, or at the ``milestones``);
    ``cosine``: stepped once per optimiser step, from lr down to 0 over the run."""
    if hyper.schedule == "cosine":
        total = max(1, hyper.epochs * steps_per_epoch)
        return torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: 0.5 * (1 + math.cos(math.pi * min(step, total) / total)))
    if hyper.step_every:
        return torch.optim.lr_scheduler.StepLR(optimizer, hyper.step_every, gamma=hyper.gamma)
    milestones = sorted({max(1, round(f * hyper.epochs)) for f in hyper.milestones})
    return torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones, gamma=hyper.gamma)
