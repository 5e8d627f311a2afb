"""The int8 form of the fused sparse segmenter: :class:`Int8MinkUNet`, built from a
:class:`models.segmenter.fused.FusedMinkUNet` and calibrated activation ranges (:mod:`models.quantized.calibration`).

- Activations are uint8 with a scale per channel: every convolution's output is ReLU'd and requantised to one
  per-tensor scale (calibrated), the network's input features to one scale and zero point per feature; a skip
  concatenation keeps each part's scale (the vector of the concatenated tensor is the two vectors joined).
- Weights are int8 with a scale per output channel: a convolution's folded float weight (BatchNorm folded) is first
  multiplied by its input's per-channel scales, then quantised symmetrically per output channel (max |w| -> 127), so
  ``sum_c q_x[c] q_w[c, o]`` times one float per output channel is the float convolution.
- Every convolution runs in :mod:`models.sparse.int8`'s kernels with the epilogue fused: the int32 sums scaled,
  bias, the residual sum (the block's input as uint8 with its scales, or the 1x1 shortcut's float output, itself an
  int8 kernel with a one-row table), ReLU and requantisation in the loop that writes the rows. The last convolution
  writes float32 (no requantisation before the classifier), and the classifier runs in float (N x 24 x classes MACs).
- Scales are given per channel (a calibration per tensor gives each channel the tensor's scale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from models.segmenter.fused import FoldedConv, FoldedResidual, FusedMinkUNet, MacTally
from models.sparse import SparseTensor, int8

QMAX_WEIGHT = 127
QMAX_ACTIVATION = 255


@dataclass(frozen=True)
class QTensor:
    """uint8 features (N, C) on the voxels of ``cache`` at ``stride``, each channel's scale (C,) and zero point (C,)
    (zero but for the input features): ``value = (feats - zero_point) * scale``."""

    feats: Tensor
    scale: Tensor
    stride: int
    cache: object
    zero_point: Tensor | None = None
    channels: Tensor | None = None
    """Where the float network's channels lie among ``feats``' columns (None: the first ones); the kernels take
    widths in multiples of 4, so each part of a tensor is padded with zero columns."""

    def positions(self) -> Tensor:
        return torch.arange(self.feats.shape[1]) if self.channels is None else self.channels

    def dequantize(self) -> Tensor:
        values = self.feats.float()
        if self.zero_point is not None:
            values = values - self.zero_point
        return values * self.scale


def padded(width: int) -> int:
    """``width`` rounded up to the kernels' multiple of 4 channels."""
    return -(-width // 4) * 4


def pad_vector(values: Tensor, width: int, fill: float) -> Tensor:
    """``values`` (n,) (or one value for all) as ``width`` values, ``fill`` past the given ones."""
    values = values.reshape(-1).float()
    if len(values) == 1:
        return values.expand(width).contiguous()
    return torch.cat([values, torch.full((width - len(values),), fill)]).contiguous()


@dataclass(frozen=True)
class InputRange:
    """The input features' calibrated range per feature: ``low`` <= 0 <= ``high`` (C,)."""

    low: Tensor
    high: Tensor

    def quantisation(self) -> tuple[Tensor, Tensor]:
        """(scale, zero point) per feature, asymmetric uint8 covering [low, high]."""
        scale = ((self.high - self.low) / QMAX_ACTIVATION).clamp(min=1e-8).float()
        zero_point = torch.round(-self.low / scale).clamp(0, QMAX_ACTIVATION)
        return scale, zero_point


@dataclass(frozen=True)
class QuantConv:
    """One convolution for the int8 kernels: packed weight, each output channel's scale of the int32 sums, bias,
    the zero-point correction per offset (or None), and the output's requantisation scale (0: float out)."""

    packed: Tensor
    scale: Tensor
    bias: Tensor
    correction: Tensor | None
    out_scale: Tensor | None
    channels: int


def quantize_weight(weight: Tensor, in_scale: Tensor) -> tuple[Tensor, Tensor]:
    """(K, C, D) float weight acting on inputs of scale ``in_scale`` (C,) -> (int8 weight, scale per output (D,))."""
    scaled = weight.float() * in_scale[None, :, None]
    scale = (scaled.abs().amax(dim=(0, 1)) / QMAX_WEIGHT).clamp(min=1e-12)
    quantised = torch.round(scaled / scale).clamp(-QMAX_WEIGHT, QMAX_WEIGHT).to(torch.int8)
    return quantised.contiguous(), scale.float().contiguous()


def quantize_conv(conv: FoldedConv, x: QTensor, out_scale: Tensor | None) -> QuantConv:
    """``conv`` on inputs quantised as ``x`` (its scales and zero points), output requantised to ``out_scale``."""
    k, _, c_out = conv.weight.shape
    full = torch.zeros(k, x.feats.shape[1], padded(c_out))
    full[:, x.positions(), :c_out] = conv.weight.float()
    weight, scale = quantize_weight(full, x.scale)
    correction = None
    if x.zero_point is not None:  # sum_c zp[c] * w[k, c, :], subtracted per present pair (zero point 1 below)
        correction = torch.einsum("c,kcd->kd", x.zero_point.long(), weight.long()).to(torch.int32).contiguous()
    return QuantConv(int8.pack_weight(weight), scale, pad_vector(conv.bias, padded(c_out), 0.0), correction, out_scale,
                     conv.channels)


@dataclass
class _Run:
    """One forward's state: the MAC tally and the index of the next activation scale."""

    macs: MacTally = field(default_factory=MacTally)
    layer: int = 0
    tables: dict[int, tuple[Tensor, Tensor]] = field(default_factory=dict)
    pair_lists: dict[int, tuple[Tensor, tuple[Tensor, Tensor, Tensor]]] = field(default_factory=dict)

    def pairs(self, neighbours: Tensor, num_in: int) -> tuple[Tensor, Tensor, Tensor]:
        """``neighbours`` as the int8 kernels' compact pairs (:func:`models.sparse.int8.compact_pairs`), built once
        per forward: a level's map serves about ten convolutions, and the kernels then never visit a missing slot
        (at 8-24 channels 1.6-2x faster than over the table, which is about half missing slots in an ROI)."""
        key = id(neighbours)
        if key not in self.pair_lists:
            self.pair_lists[key] = (neighbours, int8.compact_pairs(neighbours, num_in))
        return self.pair_lists[key][1]

    def int32(self, neighbours: Tensor) -> Tensor:
        """``neighbours`` as int32, converted once per forward (a level's map serves about ten convolutions; the
        kernels read half the index bytes)."""
        if neighbours.shape[0] >= 2**31 - 1:
            return neighbours
        key = id(neighbours)
        if key not in self.tables:
            self.tables[key] = (neighbours, neighbours.to(torch.int32))
        return self.tables[key][1]


class Int8MinkUNet:
    """``int8(x) -> (logits (N, num_classes) float32, MacTally)``, as :class:`FusedMinkUNet` is called.

    ``activation_scales``: each requantised activation's uint8 scale per channel (C,), in the order the layer walk
    (:meth:`FusedMinkUNet.walk`) produces them
    (:func:`models.quantized.calibration.calibrate` measures them on frames); ``input_range``: the input features'.
    The int8 layers are built on first use from their input's scales (constants: the same at every call)."""

    precision = "int8"

    def __init__(self, fused: FusedMinkUNet, input_range: InputRange, activation_scales: list[Tensor]) -> None:
        if not isinstance(fused, FusedMinkUNet):
            raise TypeError(f"Int8MinkUNet takes a FusedMinkUNet, got {type(fused).__name__}")
        self.activation_scales = [torch.as_tensor(s, dtype=torch.float32).reshape(-1).contiguous()
                                  for s in activation_scales]
        if not all(bool((s > 0).all()) and bool(torch.isfinite(s).all()) for s in self.activation_scales):
            raise ValueError("activation scales must be finite and > 0")
        self.fused = fused
        self.input_range = input_range
        self.num_classes = fused.num_classes
        self._layers: dict[tuple[int, str], QuantConv] = {}
        int8.load()  # build the kernels now, not inside the first frame

    def _layer(self, run: _Run, conv: FoldedConv, x: QTensor, role: str, requantize: bool = True) -> QuantConv:
        key = (run.layer, role)
        if key not in self._layers:
            out_scale = self._out_scale_vector(run, padded(conv.weight.shape[2])) if requantize else None
            self._layers[key] = quantize_conv(conv, x, out_scale)
        return self._layers[key]

    def _next(self, run: _Run) -> None:
        run.layer += 1
        if run.layer > len(self.activation_scales):
            raise ValueError(f"{len(self.activation_scales)} activation scales for a network with more activations")

    def _out_scale_vector(self, run: _Run, width: int) -> Tensor:
        return pad_vector(self.activation_scales[run.layer], width, 1.0)

    def _submanifold(self, x: QTensor, conv: FoldedConv, run: _Run, residual: QTensor | Tensor | None = None
                     ) -> QTensor:
        last = run.layer == len(self.activation_scales) - 1  # the classifier's input: kept float
        layer = self._layer(run, conv, x, "submanifold", requantize=not last)
        kernel_map = x.cache.kernel_map(x.stride, conv.kernel_size, 1)
        run.macs.add(kernel_map.num_pairs, layer.channels)
        neighbours, order = kernel_map.in_coordinate_order
        feats = x.feats if order is None else x.feats.index_select(0, order)
        residual_feats, residual_scale = (residual.feats, residual.scale) if isinstance(residual, QTensor) else (
            residual, None)
        if residual_feats is not None and order is not None:
            residual_feats = residual_feats.index_select(0, order)
        out = int8.neighbour_conv_pairs(feats, run.pairs(neighbours, len(feats)), neighbours.shape, layer.packed,
                                        layer.scale, zero_point=int(layer.correction is not None),
                                        weight_sums=layer.correction, bias=layer.bias, residual=residual_feats,
                                        residual_scale=residual_scale, relu=True, out_scale=layer.out_scale)
        if order is not None:
            out = torch.empty_like(out).index_copy_(0, order, out)
        scale = torch.ones(out.shape[1]) if last else self._out_scale_vector(run, out.shape[1])
        self._next(run)
        return QTensor(out, scale, x.stride, x.cache, channels=torch.arange(conv.weight.shape[2]))

    def _strided(self, x: QTensor, conv: FoldedConv, run: _Run) -> QTensor:
        layer = self._layer(run, conv, x, "strided")
        kernel_map = x.cache.kernel_map(x.stride, 2, 2)
        run.macs.add(kernel_map.num_pairs, layer.channels)
        pairs = run.pairs(kernel_map.neighbours, len(x.feats))
        out = int8.neighbour_conv_pairs(x.feats, pairs, kernel_map.neighbours.shape, layer.packed, layer.scale,
                                        bias=layer.bias, relu=True, out_scale=layer.out_scale)
        scale = self._out_scale_vector(run, out.shape[1])
        self._next(run)
        return QTensor(out, scale, 2 * x.stride, x.cache, channels=torch.arange(conv.weight.shape[2]))

    def _transposed(self, x: QTensor, conv: FoldedConv, run: _Run) -> QTensor:
        layer = self._layer(run, conv, x, "transposed")
        fine = x.stride // 2
        kernel_map = x.cache.kernel_map(fine, 2, 2)
        run.macs.add(kernel_map.num_pairs, layer.channels)
        out = int8.scatter_conv(x.feats, run.int32(kernel_map.neighbours), layer.packed, kernel_map.num_in, layer.scale,
                                bias=layer.bias, relu=True, out_scale=layer.out_scale)
        scale = self._out_scale_vector(run, out.shape[1])
        self._next(run)
        return QTensor(out, scale, fine, x.cache, channels=torch.arange(conv.weight.shape[2]))

    def _residual(self, x: QTensor, block: FoldedResidual, run: _Run) -> QTensor:
        hidden = self._submanifold(x, block.first, run)
        if block.shortcut is None:
            shortcut: QTensor | Tensor = x
        else:  # a 1x1 conv: one pair per voxel, float out
            layer = self._layer(run, block.shortcut, x, "shortcut", requantize=False)
            rows = torch.arange(len(x.feats), dtype=torch.int32)[:, None]
            shortcut = int8.neighbour_conv(x.feats, rows, layer.packed, layer.scale, bias=layer.bias)
            run.macs.add(len(x.feats), layer.channels)
        return self._submanifold(hidden, block.second, run, residual=shortcut)

    def _concat(self, up: QTensor, skip: QTensor) -> QTensor:
        """A skip concatenation: each part keeps its scales, the float channels' positions follow the columns."""
        positions = torch.cat([up.positions(), skip.positions() + up.feats.shape[1]])
        return QTensor(torch.cat([up.feats, skip.feats], dim=1), torch.cat([up.scale, skip.scale]), skip.stride,
                       skip.cache, channels=positions)

    def quantize_input(self, feats: Tensor, stride: int, cache: object) -> QTensor:
        """The input features (N, C) float as uint8 with their per-feature scale and zero point."""
        scale, zero_point = self.input_range.quantisation()
        quantised = torch.round(feats / scale + zero_point).clamp(0, QMAX_ACTIVATION).to(torch.uint8)
        width = padded(feats.shape[1])
        if width != feats.shape[1]:
            quantised = torch.cat([quantised, quantised.new_zeros(len(quantised), width - feats.shape[1])], dim=1)
        return QTensor(quantised.contiguous(), pad_vector(scale, width, 1.0), stride, cache,
                       pad_vector(zero_point, width, 0.0), torch.arange(feats.shape[1]))

    @torch.no_grad()
    def __call__(self, x: SparseTensor) -> tuple[Tensor, MacTally]:
        """Logits (N, num_classes) for the N voxels of ``x`` (stride 1) and the frame's MACs."""
        run = _Run()
        fused = self.fused
        x.cache.build_pyramid(x.stride, len(fused.encoder) + 1)
        y = fused.walk(self.quantize_input(x.feats.float(), x.stride, x.cache), self, run)
        if run.layer != len(self.activation_scales):
            raise ValueError(f"{len(self.activation_scales)} activation scales for {run.layer} activations")
        feats = y.feats if y.feats.dtype == torch.float32 else y.dequantize()  # the last convolution's: float
        if feats.shape[1] != fused.classifier_weight.shape[0]:
            feats = feats[:, y.positions()]
        logits = feats @ fused.classifier_weight
        if fused.classifier_bias is not None:
            logits += fused.classifier_bias
        run.macs.add(len(y.feats), fused.classifier_weight.numel())
        return logits, run.macs
