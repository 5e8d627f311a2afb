"""Checkpoints that rebuild their model alone: registry name and builder config beside the weights,
plus the radar preset, class names and input normalisation the model was trained with.

Saved with ``torch.save`` as plain containers and tensors; loaded with ``weights_only=True``, so a
checkpoint can never run code on load. A pruned (slimmed) model stores the config of its narrower
architecture, so it loads without the original.

A checkpoint says what it is: its ``stage`` (detector, segmenter or baseline), its architecture (the registry
name), its preset and the ``input_kind`` it takes (normalised log power in dB for every model we train). Files
written before these fields existed still load: the stage comes from ``extra["stage"]`` or, failing that, from
the architecture. Every command that loads a checkpoint for a stage names it and the option it came from
(``load_checkpoint(path, stage=Stage.DETECTOR, option="--detector")``), so a swapped or foreign file is one
line naming what was given and what was expected.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from models.capabilities import Stage
from models.registry import create_model
from radar.errors import UserError
from radar.profiles import BUILTIN_PRESETS, RadarProfile, resolve_profile

FORMAT = "radarseg.checkpoint"
VERSION = 1


# The stage of each architecture (registry name without its ``_tiny`` suffix): for checkpoints that predate
# the ``stage`` field and carry no ``extra["stage"]``.
STAGE_OF_ARCHITECTURE = {"centre_detector": Stage.DETECTOR, "minkunet": Stage.SEGMENTER, "spvcnn": Stage.SEGMENTER,
                         "unet": Stage.BASELINE, "tmvanet": Stage.BASELINE, "smvanet": Stage.BASELINE}
INPUT_KIND = "log_power_db"  # what every model we train takes (normalised with the checkpoint's statistics)


class CheckpointError(UserError):
    """A checkpoint file that is missing, unreadable, not a radarseg checkpoint, or not the one expected."""


def architecture_stage(model_name: str) -> Stage | None:
    """The stage of a registry name (``centre_detector_tiny`` -> ``detector``); None for an unknown one."""
    return STAGE_OF_ARCHITECTURE.get(model_name.removesuffix("_tiny"))


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
    source: str | None = field(default=None, compare=False)  # the file it was loaded from (not saved)

    @property
    def stage(self) -> Stage | None:
        """detector, segmenter or baseline (stored, or derived from the architecture for older files)."""
        stored = self.extra.get("stage")
        return Stage(stored) if stored in tuple(Stage) else architecture_stage(self.model_name)

    @property
    def input_kind(self) -> str:
        """What the model takes as input (``log_power_db``: normalised log power, radar.input_kind)."""
        return self.extra.get("input_kind", INPUT_KIND)

    @property
    def profile(self) -> RadarProfile:
        """The radar the model was trained for: a built-in preset by name, or the description the checkpoint
        carries (``extra["radar_file"]``, written by the trainers for a radar described by a file)."""
        return resolve_profile(self.preset, self.extra.get("radar_file"),
                               source=f"{self.stage or 'model'} checkpoint {self.source or ''}".rstrip())

    def describe(self) -> str:
        """``a detector checkpoint (centre_detector, preset small)``."""
        return f"a {self.stage or 'model'} checkpoint ({self.model_name}, preset {self.preset})"

    def build(self, *, device: str | torch.device = "cpu") -> nn.Module:
        """The model in eval mode with the checkpoint's weights."""
        config = dict(self.config)
        if config.get("preset") not in (None, *BUILTIN_PRESETS):  # a radar described by a file: its profile
            config["preset"] = self.profile
        self.check_size(config)
        model = create_model(self.model_name, **config)
        model.load_state_dict(self.state_dict)
        return model.to(device).eval()

    def check_size(self, config: dict[str, Any]) -> None:
        """CheckpointError when ``config`` builds a network larger than the weights the checkpoint holds (a width
        of 10**9 would allocate gigabytes before ``load_state_dict`` refused it): counted on torch's meta device,
        which allocates nothing. A builder that cannot run on the meta device is left to the real build."""
        held = sum(tensor.numel() for tensor in self.state_dict.values())
        try:
            with torch.device("meta"):
                probe = create_model(self.model_name, **config)
        except (TypeError, ValueError, KeyError) as exc:
            raise CheckpointError(f"{self.source or 'checkpoint'}: its config {config} does not build "
                                  f"{self.model_name}: {type(exc).__name__}: {exc}") from None
        except Exception:  # noqa: BLE001 (an operation the meta device lacks: the real build decides)
            return
        built = sum(t.numel() for t in probe.state_dict().values())  # counted as the file counts (no transient buffers)
        if built > 2 * held + 1024:
            raise CheckpointError(f"{self.source or 'checkpoint'}: its config builds a {self.model_name} of {built} "
                                  f"weights but the file holds {held}: refused before allocating it")

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT, "version": VERSION, "model_name": self.model_name, "config": dict(self.config),
            "state_dict": self.state_dict, "preset": self.preset, "class_names": list(self.class_names),
            "normalisation": dict(self.normalisation),
            # plain values only (torch.load(weights_only=True) refuses enum classes): a Stage as its name
            "extra": {k: str(v) if isinstance(v, Stage) else v for k, v in self.extra.items()},
            # what the file is, readable without the registry (older readers ignore these keys)
            "stage": None if self.stage is None else str(self.stage), "input_kind": self.input_kind,
        }


def save_checkpoint(checkpoint: Checkpoint, path: str | Path) -> Path:
    """Write atomically (temporary file, then rename): an interrupted save never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(checkpoint.to_dict(), tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path, *, stage: str | None = None, option: str | None = None) -> Checkpoint:
    """The checkpoint in ``path``; with ``stage``, refused (CheckpointError) unless it is one of that stage.
    ``option`` names the option it was given as (``--detector``) in the message."""
    path = Path(path)
    what = f"{option} {path}" if option else str(path)
    kind = stage or (option if option in tuple(Stage) else "model")
    expected = f"expected a radarseg {kind} checkpoint (.pt written by radarseg train)"
    if not path.is_file():
        raise CheckpointError(f"{what}: no such checkpoint file; {expected}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or unsafe files; its advice (weights_only=False
        # would run the file's code) is not relayed
        raise CheckpointError(f"{what}: not a checkpoint (torch cannot load it: {type(exc).__name__}); "
                              f"{expected}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{what}: a torch file but not a radarseg checkpoint; {expected}")
    if data.get("version") != VERSION:
        raise CheckpointError(f"{what}: checkpoint version {data.get('version')!r}, expected {VERSION}")
    checkpoint = Checkpoint(
        model_name=data["model_name"], config=dict(data["config"]), state_dict=data["state_dict"],
        preset=data["preset"], class_names=tuple(data["class_names"]),
        normalisation=dict(data["normalisation"]), extra=dict(data["extra"]), source=str(path),
    )
    for key in ("stage", "input_kind"):  # the top-level fields (written since they exist) win over a guess
        if data.get(key) and key not in checkpoint.extra:
            checkpoint.extra[key] = data[key]
    if stage is not None:
        expect_stage(checkpoint, stage, option=option)
    return checkpoint


def expect_stage(checkpoint: Checkpoint, stage: str, *, option: str | None = None) -> None:
    """CheckpointError unless ``checkpoint`` is of ``stage``, naming what was given and what was expected."""
    if stage not in tuple(Stage):
        raise ValueError(f"stage must be one of {[str(s) for s in Stage]}, got {stage!r}")
    if checkpoint.stage != stage:
        where = " ".join(part for part in (option, checkpoint.source) if part) or "checkpoint"
        raise CheckpointError(f"{where}: {checkpoint.describe()}, expected a {stage} checkpoint")


def load_pair(detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint
              ) -> tuple[Checkpoint, Checkpoint]:
    """The boundary where a pair given as files becomes two :class:`Checkpoint` (everything below takes those):
    checked to be a detector and a segmenter (CheckpointError naming a swapped pair, the same file twice, or a
    checkpoint of another stage). Cheap: nothing is built."""
    if not isinstance(detector, Checkpoint) and not isinstance(segmenter, Checkpoint):
        if Path(detector).resolve() == Path(segmenter).resolve():
            raise CheckpointError(f"the same file {detector} given as detector and as segmenter; expected a "
                                  f"detector checkpoint and a segmenter checkpoint")
    det = detector if isinstance(detector, Checkpoint) else load_checkpoint(detector, option="detector")
    seg = segmenter if isinstance(segmenter, Checkpoint) else load_checkpoint(segmenter, option="segmenter")
    if det.stage == Stage.SEGMENTER and seg.stage == Stage.DETECTOR:
        raise CheckpointError(f"detector {det.source or ''} and segmenter {seg.source or ''} are swapped: "
                              f"{det.describe()} given as detector, {seg.describe()} as segmenter")
    expect_stage(det, Stage.DETECTOR, option="detector")
    expect_stage(seg, Stage.SEGMENTER, option="segmenter")
    return det, seg


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
