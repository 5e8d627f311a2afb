"""SPVCNN: MinkUNet plus a point branch that keeps full-resolution point features (docs/design.md section 7).

Points carry continuous coordinates in units of the finest voxel: the voxel `c` (at tensor stride 1)
covers `[c, c + 1)` along each axis, so a point at a voxel's centre has coordinates `c + 0.5`, and at
tensor stride `s` voxel `c` covers `[s*c, s*(c + 1))`. RAD bins given as points therefore use
`bin + 0.5`; Cartesian points use `position / voxel_size`.

- voxelise: average the features of the points inside each voxel;
- devoxelise: trilinear interpolation between the centres of the 8 voxels around a point, weights
  renormalised over the voxels that exist (the point's own voxel always does);
- point MLPs (linear, BN, ReLU) are added to the devoxelised features after the last encoder stage and
  after decoder stages 2 and 4; the classifier runs on the points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor, nn

from models.segmenter.blocks import PointMLP
from models.segmenter.minkunet import MinkUNet
from models.sparse import SparseTensor
from models.sparse.kernel_map import check_coords, lookup, pack_keys, unpack_keys

CORNERS = torch.tensor([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=torch.int64,
                       device="cpu")  # explicit: the module may first be imported under a meta-device context
"""(8, 3) offsets of the 8 voxels around a point, relative to the lower corner."""
FUSE_AFTER_DECODER_STAGE = {1: 1, 3: 2}
"""Decoder stage (0-based) -> point MLP fused after it (MLP 0 is fused after the encoder)."""


@dataclass(frozen=True)
class PointTensor:
    """Points with continuous coordinates and features.

    Attributes:
        batch: (N,) int64 sample index of each point.
        coords: (N, 3) float coordinates in finest-voxel units (voxel c covers [c, c + 1)).
        feats: (N, C) float features.
    """

    batch: Tensor
    coords: Tensor
    feats: Tensor

    def __post_init__(self) -> None:
        n = self.batch.shape[0]
        if self.batch.ndim != 1 or self.batch.dtype != torch.int64:
            raise ValueError(f"batch must be (N,) int64, got {tuple(self.batch.shape)} {self.batch.dtype}")
        if self.coords.shape != (n, 3) or not self.coords.is_floating_point():
            raise ValueError(f"coords must be (N, 3) float with N = {n}, got {tuple(self.coords.shape)}")
        if self.feats.ndim != 2 or self.feats.shape[0] != n:
            raise ValueError(f"feats must be (N, C) with N = {n}, got {tuple(self.feats.shape)}")


def voxel_rows(points: PointTensor, x: SparseTensor) -> Tensor:
    """Row of `x` holding the voxel that contains each point at `x`'s tensor stride.

    Returns:
        (N_points,) int64.

    Raises:
        ValueError: a point lies outside every voxel of `x`.
    """
    spatial = torch.floor(points.coords / x.stride).long()
    rows, found = lookup(*x.cache.sorted_keys(x.stride), pack_keys(points.batch, spatial))
    if not bool(found.all()):
        raise ValueError(f"{int((~found).sum())} points lie outside the voxels of the sparse tensor")
    return rows


def scatter_mean(feats: Tensor, rows: Tensor, num_rows: int) -> Tensor:
    """Average of feature rows (N, C) grouped by target row (N,) -> (num_rows, C); empty rows stay 0."""
    total = feats.new_zeros(num_rows, feats.shape[1]).index_add_(0, rows, feats)
    count = torch.bincount(rows, minlength=num_rows).clamp_(min=1).to(feats.dtype)
    return total / count[:, None]


def voxelize(points: PointTensor) -> SparseTensor:
    """Stride-1 sparse tensor of the voxels that contain points, features averaged: (M, C), M <= N."""
    voxel_of_point = torch.cat([points.batch[:, None], torch.floor(points.coords).long()], dim=1)
    check_coords(voxel_of_point)  # before packing, so out-of-range points fail instead of aliasing
    keys, rows = torch.unique(pack_keys(voxel_of_point[:, 0], voxel_of_point[:, 1:]), return_inverse=True)
    return SparseTensor(unpack_keys(keys), scatter_mean(points.feats, rows, len(keys)), stride=1)


def voxelize_onto(x: SparseTensor, points: PointTensor, point_feats: Tensor) -> SparseTensor:
    """Replace the features of `x` by the average of point features (N_points, C) in each voxel."""
    return x.replace_feats(scatter_mean(point_feats, voxel_rows(points, x), len(x)))


def devoxelize(x: SparseTensor, points: PointTensor) -> Tensor:
    """Trilinear interpolation of voxel features at the points.

    Args:
        x: voxels (M, C) at tensor stride s; voxel c's centre is at s * (c + 0.5) finest-voxel units.
        points: the points (N,) the voxels were built from.

    Returns:
        (N, C) point features.
    """
    with torch.no_grad():  # the weights depend only on coordinates
        grid = points.coords / x.stride - 0.5  # position in units of voxel centres
        lower = torch.floor(grid)
        frac = grid - lower  # (N, 3) in [0, 1)
        corners = CORNERS.to(lower.device)
        spatial = lower.long()[None] + corners[:, None, :]  # (8, N, 3)
        batch = points.batch[None].expand(8, -1)
        rows, found = lookup(*x.cache.sorted_keys(x.stride), pack_keys(batch, spatial))
        axis_weights = torch.where(corners[:, None, :].bool(), frac[None], 1 - frac[None])  # (8, N, 3)
        weights = axis_weights.prod(dim=2) * found  # missing voxels weigh 0
        weights = (weights / weights.sum(dim=0, keepdim=True)).to(x.feats.dtype)
    return (x.feats[rows] * weights[..., None]).sum(dim=0)


class SPVCNN(MinkUNet):
    """MinkUNet with a point branch; logits per point.

    `forward(points)` maps a `PointTensor` with features (N, in_channels) to logits (N, num_classes).
    Stem, encoder, decoder and classifier are MinkUNet's own modules; only the point MLPs are added.
    Unlike spvnas, the stem output feeds encoder stage 1 directly instead of being devoxelised and
    re-voxelised first (the same thing when points sit at voxel centres, the RAD-bin case).
    """

    channel_tracer: ClassVar[str] = "sparse_unet_points"

    def make_input(self, coords: Tensor, feats: Tensor) -> PointTensor:  # type: ignore[override]
        """Points at the voxel centres of ``coords`` (N, 4) int64 (batch, range, angle, Doppler bins)."""
        return PointTensor(coords[:, 0].contiguous(), coords[:, 1:].to(feats.dtype) + 0.5, feats)

    def add_branches(self, widths: tuple[int, ...]) -> None:
        """The point MLPs, their widths from stages 0, 4, 6 and 8 (the constructor is `MinkUNet`'s)."""
        stem, bottleneck, decoder_2, decoder_4 = widths[0], widths[4], widths[6], widths[8]
        self.point_mlps = nn.ModuleList(
            [PointMLP(stem, bottleneck), PointMLP(bottleneck, decoder_2), PointMLP(decoder_2, decoder_4)]
        )

    def forward(self, points: PointTensor) -> Tensor:  # type: ignore[override]
        """Logits (N, num_classes) for the N points."""
        *skips, y = self.encode(voxelize(points))
        point_feats = devoxelize(skips[0], points)  # (N, w0)
        point_feats = devoxelize(y, points) + self.point_mlps[0](point_feats)  # (N, w4)
        y = voxelize_onto(y, points, point_feats)
        for stage_index, (stage, skip) in enumerate(zip(self.decoder, reversed(skips), strict=True)):
            y = stage(y, skip)
            mlp_index = FUSE_AFTER_DECODER_STAGE.get(stage_index)
            if mlp_index is not None:
                point_feats = devoxelize(y, points) + self.point_mlps[mlp_index](point_feats)
                if stage_index + 1 < len(self.decoder):
                    y = voxelize_onto(y, points, point_feats)
        return self.classifier(point_feats)
