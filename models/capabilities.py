"""What the rest of the system asks of a model, declared by the model's class (timm's way: ask the model).

Every architecture states, as class attributes and methods:

- ``role`` (:class:`Role`): which stage it is: the detector, the sparse segmenter or a 2-D baseline. The
  value is also the trainer's ``--stage`` and a checkpoint's ``extra["stage"]``.
- ``dense_input_shapes(profile)``: batch-1 input shapes for a radar profile, from which its MACs are
  counted analytically (:func:`models.compute.count_macs`); ``None`` for a model whose cost depends on
  the data (the sparse segmenters: count a real forward with :class:`models.compute.MacRecorder`).
- ``make_input(coords, feats)`` (segmenters only): its input for ROI points, ``coords`` (N, 4) int64
  (batch index, range, angle, Doppler bins) and ``feats`` (N, F): a ``SparseTensor`` for MinkUNet, a
  ``PointTensor`` for SPVCNN.
- ``channel_tracer``: the name of the tracer in :data:`models.slimming.TRACERS` that describes its
  channel ties for slimming.

Code outside ``models/`` reads these instead of testing classes; a new architecture declares them and
is usable everywhere (trainer, compare, slimming, summary, the service).
"""

from __future__ import annotations

from enum import StrEnum

from torch import nn

from radar.profiles import RadarProfile, get_profile

InputShapes = tuple[tuple[int, ...], ...]


class Role(StrEnum):
    """The stage a model plays; the values are the trainer's stages."""

    DETECTOR = "detector"
    SEGMENTER = "segmenter"
    BASELINE = "baseline"


def role_of(model: nn.Module) -> Role:
    """The :class:`Role` a model declares; ``ValueError`` for a module that declares none."""
    role = getattr(model, "role", None)
    if not isinstance(role, Role):
        raise ValueError(f"{type(model).__name__} declares no role: expected a detector, a sparse segmenter "
                         f"or a 2-D baseline of models/")
    return role


def dense_input_shapes(model: nn.Module, preset: str | RadarProfile) -> InputShapes | None:
    """Batch-1 input shapes of ``model`` at ``preset`` (None when its cost depends on the data)."""
    return model.dense_input_shapes(get_profile(preset))
