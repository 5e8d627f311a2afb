"""Calibration of the int8 segmenter: its activation ranges measured on frames, as the ONNX int8 export calibrates.

The float pipeline (:class:`models.erasenet.model.EraseNet`, fused segmenter) runs on log-power frames (a store's
train split, or simulated frames of the model's preset: :class:`models.export.export_cache.Int8Calibration`);
the segmenter's input on each frame's ROI is kept, and the fused float network runs on it once more with every
requantised activation observed: the input features' range per feature, and each ReLU'd convolution output's
maximum (``max``) or its 99.99th percentile (``percentile``), the largest over the frames: one scale per tensor, as
the ONNX export has (``per_channel=True``: one per output channel; on the shipped pair, 8 fresh frames, the labels
agreed with float's on 94.1 % of the voxels either labels as foreground both ways, so per tensor stays default).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from models.quantized.segmenter import QMAX_ACTIVATION, InputRange, Int8MinkUNet
from models.segmenter.fused import FusedMinkUNet
from models.sparse import SparseTensor
from radar.errors import UserError
from radar.input_kind import InputKind

if TYPE_CHECKING:
    from models.erasenet.model import EraseNet

METHODS = ("max", "percentile")
PERCENTILE = 0.9999
_QUANTILE_SAMPLE = 1 << 20  # torch.quantile's input is bounded: a strided sample of larger activations


class _ObservedFused(FusedMinkUNet):
    """The fused float network, each requantised activation's statistic appended to ``observed`` in the order
    :class:`Int8MinkUNet` produces them (every convolution with its ReLU; not the 1x1 shortcuts, which stay float)."""

    def __init__(self, fused: FusedMinkUNet, method: str, per_channel: bool) -> None:  # noqa: D107
        self.__dict__.update(fused.__dict__)  # shares the fused weights
        self.method = method
        self.per_channel = per_channel
        self.observed: list[Tensor] = []

    def _observe(self, out: SparseTensor) -> SparseTensor:
        feats = out.feats if self.per_channel else out.feats.reshape(-1, 1)
        if len(feats) == 0:
            self.observed.append(torch.zeros(feats.shape[1]))
        elif self.method == "max":
            self.observed.append(feats.amax(dim=0).float())
        else:
            step = max(1, len(feats) * feats.shape[1] // _QUANTILE_SAMPLE)
            self.observed.append(torch.quantile(feats[::step].float(), PERCENTILE, dim=0))
        return out

    def _submanifold(self, x, conv, macs, *, residual=None, relu=True):  # noqa: ANN001, ANN202
        return self._observe(super()._submanifold(x, conv, macs, residual=residual, relu=relu))

    def _strided(self, x, conv, macs):  # noqa: ANN001, ANN202
        return self._observe(super()._strided(x, conv, macs))

    def _transposed(self, x, conv, macs):  # noqa: ANN001, ANN202
        return self._observe(super()._transposed(x, conv, macs))


def segmenter_inputs(net: EraseNet, cubes: Sequence[np.ndarray]) -> list[SparseTensor]:
    """The segmenter's input on each frame's ROI (log-power cubes (R, A, D) dB), as the float pipeline builds it
    (frames with an empty ROI give none)."""
    inputs: list[SparseTensor] = []
    segmenter = net.segmenter
    original = segmenter.make_input

    def capture(coords: Tensor, feats: Tensor) -> SparseTensor:
        sparse = original(coords, feats)
        inputs.append(sparse)
        return sparse

    segmenter.make_input = capture  # an instance attribute: the class is untouched
    try:
        for cube in cubes:
            net.segment(np.asarray(cube, dtype=np.float32), kind=InputKind.log_power)
    finally:
        del segmenter.make_input
    return inputs


def calibrate(fused: FusedMinkUNet, inputs: Sequence[SparseTensor], method: str = "max", *,
              per_channel: bool = False) -> Int8MinkUNet:
    """The int8 network of ``fused`` with ranges measured on ``inputs`` (segmenter inputs, stride 1), one scale per
    activation tensor (``per_channel``: per channel).

    Raises:
        ValueError: an unknown method, or no input with voxels to measure on.
    """
    if method not in METHODS:
        raise ValueError(f"calibration method must be one of {METHODS}, got {method!r}")
    inputs = [x for x in inputs if len(x.feats)]
    if not inputs:
        raise UserError("int8 calibration: no calibration frame has ROI voxels (the detector found no centre on any): "
                        "calibrate on frames with objects")
    observer = _ObservedFused(fused, method, per_channel)
    per_frame: list[list[Tensor]] = []
    low = high = None
    for x in inputs:
        observer.observed = []
        with torch.no_grad():
            observer(x)
        per_frame.append(observer.observed)
        frame_low, frame_high = x.feats.float().amin(dim=0), x.feats.float().amax(dim=0)
        low = frame_low if low is None else torch.minimum(low, frame_low)
        high = frame_high if high is None else torch.maximum(high, frame_high)
    ranges = [torch.stack(frames).amax(dim=0) for frames in zip(*per_frame, strict=True)]
    scales = [r.clamp(min=1e-6) / QMAX_ACTIVATION for r in ranges]
    input_range = InputRange(low.clamp(max=0.0), high.clamp(min=0.0))
    return Int8MinkUNet(fused, input_range, scales)
