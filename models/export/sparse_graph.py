"""The MinkUNet in an export form: BatchNorms folded, every sparse conv one Gather and one MatMul.

``torch.onnx.export`` traces this module into standard ONNX operators only (Concat, Gather, Reshape,
MatMul, Add, Relu): the kernel maps are graph inputs (:mod:`models.export.kernel_maps_numpy` computes
them in numpy), so nothing in the graph depends on the voxel count but its dynamic axes.

Each conv is the implicit GEMM of ``models.sparse.conv`` (``neighbour_gemm``, ``pick_products``) without
its chunking: a submanifold or strided conv gathers all K neighbours of every output voxel (a zero row
serves the missing ones) into (N_out, K x C_in) and multiplies by the stacked weight (K x C_in, C_out), a 3^3
one through z-columns (three rows gathered once per column, then nine columns per voxel: export format 4); a
transposed conv multiplies every coarse voxel by all K weights, (N_coarse, C_in) @ (C_in, K x C_out), and
each fine voxel picks its one product. The issue's prototype measured this form 1.4-2.2x faster in
onnxruntime than eager PyTorch, and the per-offset form 2-5x slower.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from models.export.kernel_maps_numpy import STRIDES
from models.segmenter.blocks import DownBlock, ResidualBlock, UpBlock
from models.segmenter.minkunet import MinkUNet
from models.segmenter.spvcnn import SPVCNN
from models.sparse import BatchNorm, PointwiseConv, StridedConv3d, SubmanifoldConv3d, TransposedConv3d

CHUNK_BYTES = 3 << 20
"""Gathered bytes per row block of a conv in the graph. One layer in onnxruntime, one thread, 35 k ROI voxels at
stride 1 (the shipped `small` segmenter's largest frame), time against the unchunked form: 32 -> 24 channels
0.66x at 32 blocks of 3.8 MB, 24 -> 24 0.64x at 32 blocks (2.9 MB), 8 -> 8 0.75x at 16 blocks (1.9 MB), worse
at 32 (0.96 MB): the (N, K x C_in) gather is memory-bound unless its block is still in cache for the product."""
MAX_PIECES = 64
REFERENCE_VOXELS = {1: 32768, 2: 9216, 4: 2560, 8: 512, 16: 64}
"""Voxels per tensor stride the row blocks are sized for: a large ROI of the `small` preset (35,401 / 9,590 /
2,612 / 435 / 64 on the frame above). Any count works; blocks only change speed."""


def chunk_pieces(rows: int, row_bytes: int) -> int:
    """Row blocks for a gather of ``rows`` rows of ``row_bytes``: about ``CHUNK_BYTES`` each, 1 to ``MAX_PIECES``."""
    return max(1, min(MAX_PIECES, round(rows * row_bytes / CHUNK_BYTES)))


def row_blocks(table: Tensor, pieces: int) -> list[Tensor]:
    """``table`` cut into ``pieces`` consecutive row blocks of near-equal size (their sizes differ by one at most).

    Written as one Slice per block with bounds computed from the traced row count, not ``torch.tensor_split``:
    that traces to SplitToSequence / SequenceAt, whose element shapes ONNX shape inference gives one symbolic
    size for all blocks, which onnxruntime then enforces (the int8 calibration runs the shape-inferred graph
    and fails on unequal blocks), and which some runtimes (TensorRT) do not take at all."""
    rows = table.shape[0]
    bounds = [(rows * i + pieces - 1) // pieces for i in range(pieces + 1)]
    return [table[bounds[i]:bounds[i + 1]] for i in range(pieces)]


@dataclass(frozen=True)
class LayerCost:
    """One matrix product of the graph, for its MAC count: ``kind`` "gather" (rows of ``map_name``, pairs
    = its entries below the voxel count), "pick" (transposed conv over the down map ``map_name``: one pair
    per fine voxel) or "pointwise" (every voxel at ``stride``)."""

    kind: str
    map_name: str
    stride: int
    in_channels: int
    out_channels: int
    kernel_volume: int

    def to_dict(self) -> dict[str, int | str]:
        return {"kind": self.kind, "map": self.map_name, "stride": self.stride, "in_channels": self.in_channels,
                "out_channels": self.out_channels, "kernel_volume": self.kernel_volume}


def expand_in_graph(columns: Tensor, table: Tensor) -> Tensor:
    """A level's (N, 27) neighbour table from its z-columns (M, 3) and column table (N, 9), as graph operators
    (``models.export.kernel_maps_numpy.expand_neighbours``): one integer gather per level."""
    return columns[table.reshape(-1)].reshape(table.shape[0], 27)


def _fold(weight: Tensor, bias: Tensor | None, norm: nn.BatchNorm1d | None) -> tuple[Tensor, Tensor]:
    """A conv's weight (..., C_out) and bias (C_out) with the eval-mode BatchNorm after it folded in."""
    c_out = weight.shape[-1]
    bias = torch.zeros(c_out) if bias is None else bias.detach().clone()
    weight = weight.detach().clone()
    if norm is None:
        return weight, bias
    scale = norm.weight.detach() / torch.sqrt(norm.running_var + norm.eps)
    return weight * scale, (bias - norm.running_mean) * scale + norm.bias.detach()


class GatherConv(nn.Module):
    """Submanifold or strided conv (+ folded BatchNorm): ``gather(features, neighbours) @ weight + bias``.

    (N_in, C_in) and a neighbour table (N_out, K) -> (N_out, C_out)."""

    def __init__(self, conv: SubmanifoldConv3d | StridedConv3d, norm: nn.BatchNorm1d | None, relu: bool) -> None:
        super().__init__()
        weight, bias = _fold(conv.weight, conv.bias, norm)
        num_offsets, c_in, c_out = weight.shape
        self.weight = nn.Parameter(weight.reshape(num_offsets * c_in, c_out), requires_grad=False)
        self.bias = nn.Parameter(bias, requires_grad=False)
        self.relu = relu
        self.pieces = 1
        """Row blocks the gather and product run in (``chunk_pieces``): set by :class:`ExportMinkUNet`."""

    def forward(self, feats: Tensor, neighbours: Tensor, columns: Tensor | None = None) -> Tensor:
        """``columns`` (M, 3) for a 3^3 conv, whose ``neighbours`` (N_out, 9) then name columns (see
        :mod:`models.export.kernel_maps_numpy`): each column's three rows are gathered once, then 9 columns per
        voxel, the same (N_out, 27 x C_in) matrix from about half the row copies."""
        padded = torch.cat([feats, torch.zeros_like(feats[:1])])  # row N_in: the zero of a missing neighbour
        if columns is not None:  # the last column is empty: its row of the gathered columns is zeros already
            padded = padded[columns.reshape(-1)].reshape(columns.shape[0], 3 * feats.shape[1])
        if self.pieces == 1:
            out = self._gemm(padded, neighbours)
        else:  # one Gather and Gemm per block of rows: the gathered block stays in cache for its product
            out = torch.cat([self._gemm(padded, block) for block in row_blocks(neighbours, self.pieces)])
        return torch.relu(out) if self.relu else out

    def _gemm(self, padded: Tensor, neighbours: Tensor) -> Tensor:
        """One Gemm with the bias as its C input (``addmm``): the int8 graph quantises it as one QGemm with an
        int32 bias, where a MatMul and a separate Add cost a float Add between a DequantizeLinear and a
        QuantizeLinear on every block (``benchmarks/onnx_profile.py``)."""
        gathered = padded[neighbours.reshape(-1)].reshape(neighbours.shape[0], self.weight.shape[0])
        return torch.addmm(self.bias, gathered, self.weight)


class PickConv(nn.Module):
    """Transposed conv (+ folded BatchNorm + ReLU): every fine voxel picks its one product from its parent.

    (N_coarse, C_in) and slots (N_fine,) = ``8 * parent + corner`` -> (N_fine, C_out)."""

    def __init__(self, conv: TransposedConv3d, norm: nn.BatchNorm1d) -> None:
        super().__init__()
        weight, bias = _fold(conv.weight, conv.bias, norm)  # (K, C_in, C_out)
        num_offsets, c_in, c_out = weight.shape
        self.weight = nn.Parameter(weight.permute(1, 0, 2).reshape(c_in, num_offsets * c_out), requires_grad=False)
        self.bias = nn.Parameter(bias.repeat(num_offsets), requires_grad=False)  # every product carries it
        self.out_channels = c_out

    def forward(self, feats: Tensor, slots: Tensor) -> Tensor:
        products = torch.addmm(self.bias, feats, self.weight).reshape(-1, self.out_channels)  # (N_coarse * K, C_out)
        return torch.relu(products[slots])


class Pointwise(nn.Module):
    """1x1 conv (+ folded BatchNorm): (N, C_in) -> (N, C_out)."""

    def __init__(self, conv: PointwiseConv, norm: nn.BatchNorm1d | None) -> None:
        super().__init__()
        weight, bias = _fold(conv.weight.T, conv.linear.bias, norm)  # (C_in, C_out)
        self.weight = nn.Parameter(weight, requires_grad=False)
        self.bias = nn.Parameter(bias, requires_grad=False)

    def forward(self, feats: Tensor) -> Tensor:
        return torch.addmm(self.bias, feats, self.weight)  # one Gemm, as GatherConv's


class Residual(nn.Module):
    """:class:`models.segmenter.blocks.ResidualBlock` folded: relu(conv(relu(conv(x))) + shortcut(x))."""

    def __init__(self, block: ResidualBlock) -> None:
        super().__init__()
        conv1, norm1, _, conv2, norm2 = block.main
        self.conv1 = GatherConv(conv1, norm1, relu=True)
        self.conv2 = GatherConv(conv2, norm2, relu=False)
        self.shortcut = None if isinstance(block.shortcut, nn.Identity) else Pointwise(*block.shortcut)

    def forward(self, feats: Tensor, neighbours: Tensor, columns: Tensor | None) -> Tensor:
        out = self.conv2(self.conv1(feats, neighbours, columns), neighbours, columns)
        return torch.relu(out + (feats if self.shortcut is None else self.shortcut(feats)))


def _conv_bn_relu(sequence: nn.Sequential) -> tuple[nn.Module, BatchNorm]:
    conv, norm, _ = sequence
    return conv, norm


class ExportMinkUNet(nn.Module):
    """A trained :class:`MinkUNet` (eval mode) as a function of features and kernel maps.

    ``forward(features (N, C_in), *maps)`` with the maps in the order of
    :func:`models.export.kernel_maps_numpy.input_names` -> logits (N, num_classes).
    """

    def __init__(self, model: MinkUNet, *, reference_voxels: dict[int, int] | None = None,
                 column_gathers: bool = False) -> None:
        """``reference_voxels``: voxels per stride the row blocks are sized for (default ``REFERENCE_VOXELS``).
        ``column_gathers``: each 3^3 conv gathers z-columns, then 9 columns per voxel: about half the row copies,
        the exported form (export format 6) for float and int8 (int8: 0.75x its time). Otherwise each level's
        27-row table is expanded from the columns once in the graph and every conv gathers 27 rows (the float
        graph's form up to format 5: the column form, which moves 15 % more bytes, ran 1.08x its time on an Intel
        Xeon, but 0.85-0.87x on an AMD EPYC, where onnxruntime's Gather costs about 8 ns a row whatever its width,
        16-96 bytes, so the row count decides). Same inputs either way."""
        super().__init__()
        self.column_gathers = column_gathers
        if isinstance(model, SPVCNN) or type(model) is not MinkUNet:
            raise ValueError(f"ONNX export supports MinkUNet segmenters, got {type(model).__name__}")
        if model.training:
            raise ValueError("export a model in eval mode (BatchNorm statistics are folded into the convs)")
        self.stem = nn.ModuleList(GatherConv(*_conv_bn_relu(seq), relu=True) for seq in model.stem)
        self.down = nn.ModuleList()
        self.encoder = nn.ModuleList()
        for stage in model.encoder:
            assert isinstance(stage, DownBlock)
            head, stack = stage
            self.down.append(GatherConv(*_conv_bn_relu(head), relu=True))
            self.encoder.append(nn.ModuleList(Residual(block) for block in stack))
        self.up = nn.ModuleList()
        self.decoder = nn.ModuleList()
        for stage in model.decoder:
            assert isinstance(stage, UpBlock)
            self.up.append(PickConv(*_conv_bn_relu(stage.up)))
            self.decoder.append(nn.ModuleList(Residual(block) for block in stage.fuse))
        self.classifier = Pointwise(model.classifier, None)
        reference = REFERENCE_VOXELS if reference_voxels is None else reference_voxels
        gathers = [cost for cost in self.layer_costs() if cost.kind == "gather"]
        for cost, conv in zip(gathers, self._gather_convs(), strict=True):
            conv.pieces = chunk_pieces(reference[cost.stride], conv.weight.shape[0] * 4)
        self.in_channels = model.config["in_channels"]
        self.num_classes = model.config["num_classes"]

    def forward(self, feats: Tensor, *maps: Tensor) -> Tensor:
        levels = len(STRIDES)
        columns, neighbours = list(maps[:levels]), list(maps[levels:2 * levels])
        down, up = maps[2 * levels:3 * levels - 1], maps[3 * levels - 1:]
        if not self.column_gathers:
            neighbours = [expand_in_graph(c, n) for c, n in zip(columns, neighbours, strict=True)]
            columns = [None] * levels
        y = feats
        for conv in self.stem:
            y = conv(y, neighbours[0], columns[0])
        skips = [y]
        for level, (conv, blocks) in enumerate(zip(self.down, self.encoder, strict=True)):
            y = conv(y, down[level])
            for block in blocks:
                y = block(y, neighbours[level + 1], columns[level + 1])
            skips.append(y)
        skips.pop()
        for step, (conv, blocks) in enumerate(zip(self.up, self.decoder, strict=True)):
            level = levels - 2 - step  # the finer stride this stage up-samples to
            y = torch.cat([conv(y, up[level]), skips[level]], dim=1)
            for block in blocks:
                y = block(y, neighbours[level], columns[level])
        return self.classifier(y)

    def _gather_convs(self) -> list[GatherConv]:
        """The gather convs in the order of ``layer_costs``' gather entries."""
        convs: list[GatherConv] = list(self.stem)
        for conv, blocks in zip(self.down, self.encoder, strict=True):
            convs.append(conv)
            convs += [c for block in blocks for c in (block.conv1, block.conv2)]
        for blocks in self.decoder:
            convs += [c for block in blocks for c in (block.conv1, block.conv2)]
        return convs

    def layer_costs(self) -> list[LayerCost]:
        """Every matrix product with its map, for MAC counts (see :class:`LayerCost`)."""
        costs: list[LayerCost] = []

        def gather(conv: GatherConv, map_name: str, stride: int, volume: int) -> None:
            costs.append(LayerCost("gather", map_name, stride, conv.weight.shape[0] // volume,
                                   conv.weight.shape[1], volume))

        def residual(block: Residual, stride: int) -> None:
            gather(block.conv1, f"neighbours_s{stride}", stride, 27)
            gather(block.conv2, f"neighbours_s{stride}", stride, 27)
            if block.shortcut is not None:
                costs.append(LayerCost("pointwise", "", stride, *block.shortcut.weight.shape, 1))

        for conv in self.stem:
            gather(conv, "neighbours_s1", 1, 27)
        for level, (conv, blocks) in enumerate(zip(self.down, self.encoder, strict=True)):
            gather(conv, f"down_s{STRIDES[level]}", STRIDES[level + 1], 8)
            for block in blocks:
                residual(block, STRIDES[level + 1])
        for step, (conv, blocks) in enumerate(zip(self.up, self.decoder, strict=True)):
            stride = STRIDES[len(STRIDES) - 2 - step]
            costs.append(LayerCost("pick", f"down_s{stride}", stride, conv.weight.shape[0], conv.out_channels, 8))
            for block in blocks:
                residual(block, stride)
        costs.append(LayerCost("pointwise", "", 1, *self.classifier.weight.shape, 1))
        return costs
