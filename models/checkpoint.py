"""Checkpoints that rebuild their model alone: registry name and builder config beside the weights,
plus the radar preset, class names and input normalisation the model was trained with.

Saved with ``torch.save`` as plain containers and tensors; loaded with ``weights_only=True``, so a
checkpoint can never run code on load. A pruned (slimmed) model stores the config of its narrower
architecture, so it loads without the original.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from models.registry import create_model
from radar.errors import UserError

FORMAT = "radarseg.checkpoint"
VERSION = 1


class CheckpointError(UserError):
    """A checkpoint file that is missing, unreadable or not a radarseg checkpoint."""


@dataclass
class Checkpoint:
    """Everything needed to rebuild and use a model."""

    model_name: str  # registry name
    config: dict[str, Any]  # keyword arguments of the registered builder
    state_dict: dict[str, torch.Tensor]
    preset: str
    class_names: tuple[str, ...]  # including background at index 0
    normalisation: dict[str, float] = field(default_factory=lambda: {"mean": 0.0, "std": 1.0})  # of log power (dB)
    extra: dict[str, Any] = field(default_factory=dict)  # epoch, metrics, optimiser config, ...

    def build(self, *, device: str | torch.device = "cpu") -> nn.Module:
        """The model in eval mode with the checkpoint's weights."""
        model = create_model(self.model_name, **self.config)
        model.load_state_dict(self.state_dict)
        return model.to(device).eval()

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT, "version": VERSION, "model_name": self.model_name, "config": dict(self.config),
            "state_dict": self.state_dict, "preset": self.preset, "class_names": list(self.class_names),
            "normalisation": dict(self.normalisation), "extra": dict(self.extra),
        }


def save_checkpoint(checkpoint: Checkpoint, path: str | Path) -> Path:
    """Write atomically (temporary file, then rename): an interrupted save never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(checkpoint.to_dict(), tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path) -> Checkpoint:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or unsafe files
        raise CheckpointError(f"{path}: not a loadable radarseg checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a radarseg checkpoint (expected format {FORMAT!r})")
    if data.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {data.get('version')!r}, expected {VERSION}")
    return Checkpoint(
        model_name=data["model_name"], config=dict(data["config"]), state_dict=data["state_dict"],
        preset=data["preset"], class_names=tuple(data["class_names"]),
        normalisation=dict(data["normalisation"]), extra=dict(data["extra"]),
    )


def export_checkpoint(source: str | Path, target: str | Path, *, float16: bool = True) -> Path:
    """Write a shippable copy of a training checkpoint: weights only (no optimiser state), floating
    tensors in float16 when ``float16`` (half the size; :meth:`Checkpoint.build` loads them back into the
    float32 model). Returns ``target``."""
    checkpoint = load_checkpoint(source)
    extra = {k: v for k, v in checkpoint.extra.items() if k not in ("optimizer", "scheduler")}
    return save_checkpoint(stored_as(dataclasses.replace(checkpoint, extra=extra), float16=float16), target)


def stores_float16(checkpoint: Checkpoint) -> bool:
    """Whether the checkpoint's floating weights are stored in float16 (an exported, shippable copy)."""
    floating = [v for v in checkpoint.state_dict.values() if v.is_floating_point()]
    return bool(floating) and all(v.dtype == torch.float16 for v in floating)


def stored_as(checkpoint: Checkpoint, *, float16: bool) -> Checkpoint:
    """A copy whose floating tensors are stored in float16 (``float16``) or float32, ``extra["stored_dtype"]``
    saying which; :meth:`Checkpoint.build` loads either into the float32 model."""
    dtype = torch.float16 if float16 else torch.float32
    state = {k: (v.to(dtype) if v.is_floating_point() else v) for k, v in checkpoint.state_dict.items()}
    extra = {**checkpoint.extra, "stored_dtype": "float16" if float16 else "float32"}
    return dataclasses.replace(checkpoint, state_dict=state, extra=extra)
