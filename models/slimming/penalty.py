"""Sparsity training for slimming: the L1 penalty on BatchNorm scales that the trainers add to the loss
(``lambda * penalty``, ``--slim-lambda``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from models.channel_surgery import NORM_TYPES


# --------------------------------------------------------------------------- sparsity training
def batch_norms(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """Every affine BatchNorm of ``model`` (dense and sparse), with its module path."""
    return [(name, m) for name, m in model.named_modules() if isinstance(m, NORM_TYPES) and m.affine]


def slimming_penalty(model: nn.Module) -> Tensor:
    """L1 norm of all BatchNorm scales: ``sum |gamma|`` (a scalar on the scales' device, differentiable)."""
    scales = [m.weight.abs().sum() for _, m in batch_norms(model)]
    if not scales:
        raise ValueError(f"{type(model).__name__} has no BatchNorm: nothing to slim")
    return torch.stack(scales).sum()
