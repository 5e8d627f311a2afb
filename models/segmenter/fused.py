"""The inference form of the sparse segmenter (MinkUNet), as ``FrozenDetector`` is the detector's.

Built once from a trained model in eval mode (a copy of its weights taken then):

- every BatchNorm is folded into the convolution before it: ``W'[k, :, o] = W[k, :, o] * s[o]`` and
  ``b'[o] = beta[o] - mean[o] * s[o]`` with ``s = gamma / sqrt(var + eps)`` (and the shortcut's 1x1 conv likewise);
- the ReLU after a convolution, and a residual block's sum with its shortcut and the ReLU after it, are applied by
  the compiled kernel in the loop that writes the output rows (``compiled.neighbour_conv_fused``,
  ``scatter_conv_fused``): no separate pass over the features, no module calls;
- every level's coordinates and kernel maps are built in one compiled pass before the first layer
  (``KernelMapCache.build_pyramid``);
- the frame's MACs come from the kernel maps: each convolution adds its map's pairs times its ``C_in x C_out``
  (the useful MACs, as the eager model's per-layer counters give; the compiled kernels execute exactly these),
  without per-layer hooks.

Under the reference engine (``RADARSEG_SPARSE_KERNELS=reference``, or a device or dtype the compiled engine does not
take) the same folded layers run through :func:`models.sparse.paths.apply_kernel_map` with the epilogue in PyTorch,
so the fused form runs wherever the eager one does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, TypeVar

import torch
from torch import Tensor, nn

from models.segmenter.blocks import DownBlock, ResidualBlock, UpBlock
from models.segmenter.minkunet import MinkUNet
from models.sparse import (
    BatchNorm,
    PointwiseConv,
    SparseTensor,
    StridedConv3d,
    TransposedConv3d,
    cat_features,
    compiled,
)
from models.sparse.functions import compiled_applies
from models.sparse.paths import apply_kernel_map


@dataclass(frozen=True)
class FoldedConv:
    """A convolution with its BatchNorm folded in: weight (K, C_in, C_out) and bias (C_out,), float32."""

    weight: Tensor
    bias: Tensor
    kernel_size: int  # 3 (submanifold), 2 (strided or transposed), 1 (pointwise)

    @property
    def channels(self) -> int:
        """C_in x C_out: the MACs of one pair."""
        return self.weight.shape[1] * self.weight.shape[2]


def fold(conv: nn.Module, bn: nn.BatchNorm1d) -> FoldedConv:
    """``bn(conv(x))`` as one convolution (eval statistics)."""
    if isinstance(conv, PointwiseConv):
        weight = conv.weight.detach().T[None]  # (1, C_in, C_out)
        bias = conv.linear.bias
        kernel_size = 1
    else:
        weight, bias, kernel_size = conv.weight.detach(), conv.bias, conv.kernel_size
    scale = bn.weight.detach() / torch.sqrt(bn.running_var + bn.eps)
    shift = bn.bias.detach() - bn.running_mean * scale
    if bias is not None:
        shift = shift + bias.detach() * scale
    return FoldedConv((weight * scale).float().contiguous(), shift.float().contiguous(), kernel_size)


def _conv_bn_relu(block: nn.Sequential) -> FoldedConv:
    conv, bn, relu = block
    if not (isinstance(bn, BatchNorm) and isinstance(relu, nn.Module)):
        raise TypeError(f"expected conv -> BatchNorm -> ReLU, got {block}")
    return fold(conv, bn)


@dataclass(frozen=True)
class FoldedResidual:
    """A residual block: two folded 3^3 convs, and the folded 1x1 shortcut (None: identity)."""

    first: FoldedConv
    second: FoldedConv
    shortcut: FoldedConv | None


def _residual(block: ResidualBlock) -> FoldedResidual:
    conv1, bn1, _, conv2, bn2 = block.main
    shortcut = None if isinstance(block.shortcut, nn.Identity) else fold(*block.shortcut)
    return FoldedResidual(fold(conv1, bn1), fold(conv2, bn2), shortcut)


@dataclass
class MacTally:
    """A frame's MACs: useful (pairs x C_in x C_out, per kernel map) and executed by the kernels (the same on the
    compiled engine; the reference engine's GEMM path also multiplies missing neighbours)."""

    useful: int = 0
    executed: int = 0

    def add(self, pairs: int, channels: int, executed: int | None = None) -> None:
        self.useful += pairs * channels
        self.executed += pairs * channels if executed is None else executed


Features = TypeVar("Features")
State = TypeVar("State", contravariant=True)


class LayerRunner(Protocol[Features, State]):
    """What :meth:`FusedMinkUNet.walk` runs each layer with, on its own kind of features and one frame's ``state``:
    the float network itself (``SparseTensor``, its ``MacTally``), or ``models.quantized.segmenter.Int8MinkUNet``
    (uint8 ``QTensor``, its run)."""

    def _submanifold(self, x: Features, conv: FoldedConv, state: State, /) -> Features: ...

    def _strided(self, x: Features, conv: FoldedConv, state: State, /) -> Features: ...

    def _transposed(self, x: Features, conv: FoldedConv, state: State, /) -> Features: ...

    def _residual(self, x: Features, block: FoldedResidual, state: State, /) -> Features: ...

    def _concat(self, up: Features, skip: Features, /) -> Features: ...


class FusedMinkUNet:
    """A trained :class:`MinkUNet` for inference: ``fused(x) -> (logits (N, num_classes), useful MACs)``. Equal to
    the eager model up to float rounding (the folded BatchNorms)."""

    def __init__(self, model: MinkUNet) -> None:
        if not isinstance(model, MinkUNet) or type(model) is not MinkUNet:
            raise TypeError(f"FusedMinkUNet takes a MinkUNet, got {type(model).__name__}")
        if model.training:
            raise ValueError("fuse a model in eval mode (its BatchNorms' running statistics are folded)")
        self.stem = [_conv_bn_relu(block) for block in model.stem]
        self.encoder: list[tuple[FoldedConv, list[FoldedResidual]]] = []
        for stage in model.encoder:
            assert isinstance(stage, DownBlock)
            down, stack = stage
            if not isinstance(down[0], StridedConv3d):
                raise TypeError(f"expected a strided conv, got {down[0]}")
            self.encoder.append((_conv_bn_relu(down), [_residual(b) for b in stack]))
        self.decoder: list[tuple[FoldedConv, list[FoldedResidual]]] = []
        for stage in model.decoder:
            assert isinstance(stage, UpBlock)
            if not isinstance(stage.up[0], TransposedConv3d):
                raise TypeError(f"expected a transposed conv, got {stage.up[0]}")
            self.decoder.append((_conv_bn_relu(stage.up), [_residual(b) for b in stage.fuse]))
        for conv in self.stem:
            if conv.kernel_size != 3:
                raise TypeError("expected 3^3 submanifold convs in the stem")
        classifier = model.classifier.linear
        self.classifier_weight = classifier.weight.detach().float().T.contiguous()  # (C, num_classes)
        self.classifier_bias = classifier.bias.detach().float() if classifier.bias is not None else None
        self.num_classes = classifier.out_features

    # ----------------------------------------------------------------- layers
    def _submanifold(self, x: SparseTensor, conv: FoldedConv, macs: MacTally, *, residual: Tensor | None = None,
                     relu: bool = True) -> SparseTensor:
        kernel_map = x.cache.kernel_map(x.stride, conv.kernel_size, 1)
        if compiled_applies(kernel_map, x.feats, conv.weight):
            macs.add(kernel_map.num_pairs, conv.channels)
            neighbours, order = kernel_map.in_coordinate_order
            feats = x.feats if order is None else x.feats.index_select(0, order)
            if residual is not None and order is not None:
                residual = residual.index_select(0, order)
            out = compiled.neighbour_conv_fused(feats, neighbours, conv.weight, conv.bias, residual, relu)
            if order is not None:
                out = torch.empty_like(out).index_copy_(0, order, out)
            return x.replace_feats(out)
        out, _, executed = apply_kernel_map(x.feats, conv.weight, kernel_map, transposed=False)
        macs.add(kernel_map.num_pairs, conv.channels, executed)
        return x.replace_feats(_epilogue(out, conv.bias, residual, relu))

    def _strided(self, x: SparseTensor, conv: FoldedConv, macs: MacTally) -> SparseTensor:
        kernel_map = x.cache.kernel_map(x.stride, 2, 2)
        if compiled_applies(kernel_map, x.feats, conv.weight):
            macs.add(kernel_map.num_pairs, conv.channels)
            out = compiled.neighbour_conv_fused(x.feats, kernel_map.neighbours, conv.weight, conv.bias, None, True)
        else:
            out, _, executed = apply_kernel_map(x.feats, conv.weight, kernel_map, transposed=False)
            macs.add(kernel_map.num_pairs, conv.channels, executed)
            out = _epilogue(out, conv.bias, None, True)
        coarse = 2 * x.stride
        return SparseTensor(x.cache.coords(coarse), out, coarse, cache=x.cache)

    def _transposed(self, x: SparseTensor, conv: FoldedConv, macs: MacTally) -> SparseTensor:
        fine = x.stride // 2
        kernel_map = x.cache.kernel_map(fine, 2, 2)
        if compiled.use_compiled(x.feats, conv.weight):
            macs.add(kernel_map.num_pairs, conv.channels)
            out = compiled.scatter_conv_fused(x.feats, kernel_map.neighbours, conv.weight, kernel_map.num_in,
                                              conv.bias, True)
        else:
            out, _, executed = apply_kernel_map(x.feats, conv.weight, kernel_map, transposed=True)
            macs.add(kernel_map.num_pairs, conv.channels, executed)
            out = _epilogue(out, conv.bias, None, True)
        return SparseTensor(x.cache.coords(fine), out, fine, cache=x.cache)

    def _residual(self, x: SparseTensor, block: FoldedResidual, macs: MacTally) -> SparseTensor:
        hidden = self._submanifold(x, block.first, macs)
        if block.shortcut is None:
            shortcut = x.feats
        else:  # a 1x1 conv: one pair per voxel
            shortcut = torch.addmm(block.shortcut.bias, x.feats, block.shortcut.weight[0])
            macs.add(len(x), block.shortcut.channels)
        return self._submanifold(hidden, block.second, macs, residual=shortcut.contiguous(), relu=True)

    def _concat(self, up: SparseTensor, skip: SparseTensor) -> SparseTensor:
        return cat_features([up, skip])

    # ----------------------------------------------------------------- the network
    def walk(self, x: Features, layers: LayerRunner[Features, State], state: State) -> Features:
        """The features the classifier reads: the stem, each encoder level (its strided conv, then its residual
        blocks; each level's output kept for its skip), each decoder level (its transposed conv, the skip
        concatenated, its residual blocks), every layer run by ``layers``."""
        for conv in self.stem:
            x = layers._submanifold(x, conv, state)
        skips = [x]
        for down, stack in self.encoder:
            x = layers._strided(skips[-1], down, state)
            for block in stack:
                x = layers._residual(x, block, state)
            skips.append(x)
        y = skips.pop()
        for (up, stack), skip in zip(self.decoder, reversed(skips), strict=True):
            y = layers._concat(layers._transposed(y, up, state), skip)
            for block in stack:
                y = layers._residual(y, block, state)
        return y

    @torch.no_grad()
    def __call__(self, x: SparseTensor) -> tuple[Tensor, MacTally]:
        """Logits (N, num_classes) for the N voxels of ``x`` (stride 1) and the frame's MACs."""
        macs = MacTally()
        x.cache.build_pyramid(x.stride, len(self.encoder) + 1)  # every level's kernel maps in one compiled pass
        y = self.walk(x, self, macs)
        logits = y.feats @ self.classifier_weight
        if self.classifier_bias is not None:
            logits += self.classifier_bias
        macs.add(len(y), self.classifier_weight.numel())
        return logits, macs


def _epilogue(out: Tensor, bias: Tensor, residual: Tensor | None, relu: bool) -> Tensor:
    out = out + bias
    if residual is not None:
        out += residual
    return torch.relu_(out) if relu else out


def fusable(model: nn.Module) -> bool:
    """Whether :class:`FusedMinkUNet` takes this model (a plain MinkUNet; SPVCNN and pruned variants of other
    classes run eager)."""
    return type(model) is MinkUNet

