"""Building blocks shared by the sparse segmenters (MinkUNet and SPVCNN).

All blocks take and return a `SparseTensor` (the point MLP takes point features (N, C)). Convs carry
no bias because a BatchNorm follows each of them.
"""

from __future__ import annotations

from torch import nn

from models.sparse import (
    BatchNorm,
    PointwiseConv,
    ReLU,
    SparseTensor,
    StridedConv3d,
    SubmanifoldConv3d,
    TransposedConv3d,
    cat_features,
)


def conv_bn_relu(conv: nn.Module, out_channels: int) -> nn.Sequential:
    """conv -> BatchNorm -> ReLU on a sparse tensor."""
    return nn.Sequential(conv, BatchNorm(out_channels), ReLU(inplace=True))


def submanifold_bn_relu(in_channels: int, out_channels: int) -> nn.Sequential:
    """3^3 submanifold conv -> BN -> ReLU: (N, C_in) -> (N, C_out) on the same voxels."""
    return conv_bn_relu(SubmanifoldConv3d(in_channels, out_channels, 3), out_channels)


class ResidualBlock(nn.Module):
    """Two 3^3 submanifold convs with BN, plus a shortcut (identity, or 1x1 conv + BN when widths differ).

    (N, C_in) -> (N, C_out) on the same voxels.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            SubmanifoldConv3d(in_channels, out_channels, 3),
            BatchNorm(out_channels),
            ReLU(inplace=True),
            SubmanifoldConv3d(out_channels, out_channels, 3),
            BatchNorm(out_channels),
        )
        if in_channels == out_channels:
            self.shortcut: nn.Module = nn.Identity()
        else:
            self.shortcut = nn.Sequential(PointwiseConv(in_channels, out_channels), BatchNorm(out_channels))
        self.relu = ReLU(inplace=True)

    def forward(self, x: SparseTensor) -> SparseTensor:
        out = self.main(x)
        return self.relu(out.replace_feats(out.feats + self.shortcut(x).feats))


def residual_stack(in_channels: int, out_channels: int, num_blocks: int) -> nn.Sequential:
    """`num_blocks` residual blocks, the first changing the width from `in_channels` to `out_channels`."""
    widths = [in_channels] + [out_channels] * num_blocks
    return nn.Sequential(*(ResidualBlock(a, b) for a, b in zip(widths[:-1], widths[1:], strict=True)))


class DownBlock(nn.Sequential):
    """Encoder stage: 2^3 stride-2 conv + BN + ReLU, then residual blocks.

    (N, C_in) at tensor stride s -> (M, C_out) at stride 2s.
    """

    def __init__(self, in_channels: int, out_channels: int, *, num_blocks: int = 2) -> None:
        super().__init__(
            conv_bn_relu(StridedConv3d(in_channels, in_channels), in_channels),
            residual_stack(in_channels, out_channels, num_blocks),
        )


class UpBlock(nn.Module):
    """Decoder stage: 2^3 transposed conv + BN + ReLU, concatenation with the skip, residual blocks.

    (M, C_in) at tensor stride 2s and the skip (N, C_skip) at stride s -> (N, C_out) at stride s.
    """

    def __init__(self, in_channels: int, skip_channels: int, out_channels: int, *, num_blocks: int = 2) -> None:
        super().__init__()
        self.up = conv_bn_relu(TransposedConv3d(in_channels, out_channels), out_channels)
        self.fuse = residual_stack(out_channels + skip_channels, out_channels, num_blocks)

    def forward(self, x: SparseTensor, skip: SparseTensor) -> SparseTensor:
        return self.fuse(cat_features([self.up(x), skip]))


class PointMLP(nn.Sequential):
    """SPVCNN point transform: linear -> BatchNorm1d -> ReLU on point features (N, C_in) -> (N, C_out)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__(PointwiseConv(in_channels, out_channels), nn.BatchNorm1d(out_channels), nn.ReLU(inplace=True))
