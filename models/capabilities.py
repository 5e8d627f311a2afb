"""What the rest of the system asks of a model, declared by the model's class (timm's way: ask the model).

Every architecture states, as class attributes and methods:

- ``stage`` (:class:`Stage`): which stage it is: the detector, the sparse segmenter or a 2-D baseline. The
  value is also the trainer's stage and a checkpoint's ``stage``.
- ``dense_input_shapes(profile)``: batch-1 input shapes for a radar profile, from which its MACs are
  counted analytically (:func:`models.compute.count_macs`); ``None`` for a model whose cost depends on
  the data (the sparse segmenters: count a real forward with :class:`models.compute.MacRecorder`).
- ``make_input(coords, feats)`` (segmenters only): its input for ROI points, ``coords`` (N, 4) int64
  (batch index, range, angle, Doppler bins) and ``feats`` (N, F): a ``SparseTensor`` for MinkUNet, a
  ``PointTensor`` for SPVCNN.
- ``channel_tracer``: the name of the tracer in :data:`models.slimming.channels.TRACERS` that describes its
  channel ties for slimming.

Code outside ``models/`` reads these instead of testing classes; a new architecture declares them and
is usable everywhere (trainer, compare, slimming, summary, the service).
"""

from __future__ import annotations

from enum import StrEnum
from typing import TYPE_CHECKING

from radar.profiles import RadarProfile, get_profile

if TYPE_CHECKING:  # annotations only: the stages are read by the command line's options, which load no torch
    from torch import nn

InputShapes = tuple[tuple[int, ...], ...]


class Stage(StrEnum):
    """The stage a model plays: the one name of the concept, used by models, checkpoints, trainers and jobs."""

    DETECTOR = "detector"
    SEGMENTER = "segmenter"
    BASELINE = "baseline"


ERASENET_STAGES = (Stage.DETECTOR, Stage.SEGMENTER)  # the two stages of the end-to-end model, in order


def stage_of(model: nn.Module) -> Stage:
    """The :class:`Stage` a model declares; ``ValueError`` for a module that declares none."""
    stage = getattr(model, "stage", None)
    if not isinstance(stage, Stage):
        raise ValueError(f"{type(model).__name__} declares no stage: expected a detector, a sparse segmenter "
                         f"or a 2-D baseline of models/")
    return stage


def dense_input_shapes(model: nn.Module, preset: str | RadarProfile) -> InputShapes | None:
    """Batch-1 input shapes of ``model`` at ``preset`` (None when its cost depends on the data)."""
    return model.dense_input_shapes(get_profile(preset))
