"""EfficientNet-B0 MBConv backbone, declared as a stage table and built by :func:`build_efficientnet`.

The table is docs/design.md section 5's: stem 32 channels stride 2, then stages (expand, kernel, stride,
channels, repeats) (1,3,1,16,1) (6,3,2,24,2) (6,5,2,40,2) (6,3,2,80,3) (6,5,1,112,3) (6,5,2,192,4)
(6,3,1,320,1); SE 0.25 of the block input; SiLU; BN momentum 0.01 (PyTorch convention), eps 1e-3.
No 1280-channel head conv and no classifier: the backbone returns feature maps.

Features are tapped at strides 4, 8, 16 and 32 (outputs of stages 2, 3, 5 and 7), ``(B, C_s, H_s,
W_s)`` with ``H_s = ceil(H / s)``.

"Smaller" variants (docs/design.md section 5), measured with ``benchmarks/detector.py`` as the whole detector
(Doppler 1x1 conv 64 -> 3, backbone on the 5 x 256 x 256 image, BiFPN D0 whose last layer keeps only
the top-down path, stride-4 fusion, CenterNet heads) at the ``carrada`` preset, batch 1, MACs as
``FlopCounterMode`` FLOPs / 2 (the Doppler 1x1 conv adds 0.013 G of them):

================  ==================================================  =======  =====  =========
variant           backbone change / head 3x3 convs                    params   GMACs  GMACs nxp
================  ==================================================  =======  =====  =========
``b0``            none / dense                                        3.861 M  1.007  3.398
``slim``          last three stages x2/3 channels / dense             2.094 M  0.865  2.911
``slim_sep``      ``slim`` / depthwise-separable                      1.997 M  0.470  1.601
``literal``       ``slim`` + stages 4-6 one repeat fewer / dense      1.631 M  0.812  2.730
``literal_sep``   ``literal`` / depthwise-separable                   1.534 M  0.416  1.419
================  ==================================================  =======  =====  =========

Paper: 2.08 M params, 0.49 GMACs (256 x 256), 1.46 GMACs (424 x 512). Dense 3x3 heads at stride 4
cost 0.45 GMACs on their own at 256 x 256, so only the separable-head readings get near 0.49. The
closest (sum of relative errors, -4 % and -4 %) is ``slim_sep``, the default (``SMALLER_VARIANT`` in
``centre_detector.py``): two thirds of the channels in the last three stages (112/192/320 -> 72/128/216
after rounding to multiples of 8), repeats unchanged, depthwise-separable 3x3 convs in the heads.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from torch import nn

from models.layers import ConvBnAct, SqueezeExcite, batch_norm, make_divisible


@dataclass(frozen=True)
class MBConvStage:
    """One row of the stage table: ``repeats`` MBConv blocks, the first with ``stride``."""

    expand: int
    kernel: int
    stride: int
    channels: int
    repeats: int


B0_STEM_CHANNELS = 32
B0_STAGES: tuple[MBConvStage, ...] = (
    MBConvStage(1, 3, 1, 16, 1),
    MBConvStage(6, 3, 2, 24, 2),
    MBConvStage(6, 5, 2, 40, 2),
    MBConvStage(6, 3, 2, 80, 3),
    MBConvStage(6, 5, 1, 112, 3),
    MBConvStage(6, 5, 2, 192, 4),
    MBConvStage(6, 3, 1, 320, 1),
)
# Stage indices (0-based) whose outputs are the stride 4, 8, 16, 32 features.
B0_FEATURE_STAGES: tuple[int, ...] = (1, 2, 4, 6)


def smaller_stages(
    stages: Sequence[MBConvStage] = B0_STAGES,
    *,
    channel_scale: float = 2 / 3,
    scaled_stages: Sequence[int] = (4, 5, 6),
    fewer_repeats: Sequence[int] = (),
) -> tuple[MBConvStage, ...]:
    """The stage table with ``channel_scale`` applied to ``scaled_stages`` and one repeat fewer in
    ``fewer_repeats`` (0-based stage indices; the paper's "stages 4-6" are indices 3, 4, 5).

    Channels are rounded with :func:`make_divisible` (multiples of 8).
    """
    if not 0 < channel_scale <= 1:
        raise ValueError(f"channel_scale must be in (0, 1], got {channel_scale}")
    for index in (*scaled_stages, *fewer_repeats):
        if not 0 <= index < len(stages):
            raise ValueError(f"stage index {index} out of range for a {len(stages)}-stage table")
    out = []
    for index, stage in enumerate(stages):
        if index in scaled_stages:
            stage = replace(stage, channels=make_divisible(stage.channels * channel_scale))
        if index in fewer_repeats:
            if stage.repeats < 2:
                raise ValueError(f"stage {index} has {stage.repeats} repeat(s): cannot remove one")
            stage = replace(stage, repeats=stage.repeats - 1)
        out.append(stage)
    return tuple(out)


class MBConv(nn.Module):
    """Inverted residual block: [1x1 expand] -> k x k depthwise (stride) -> SE -> 1x1 project.

    ``(B, C_in, H, W) -> (B, C_out, ceil(H / stride), ceil(W / stride))``; residual when the shape
    is kept.
    """

    def __init__(
        self, in_channels: int, out_channels: int, *, expand: int, kernel: int, stride: int, se_ratio: float
    ) -> None:
        super().__init__()
        mid = in_channels * expand
        self.expand = ConvBnAct(in_channels, mid, 1) if expand != 1 else nn.Identity()
        self.depthwise = ConvBnAct(mid, mid, kernel, stride=stride, groups=mid)
        self.se = SqueezeExcite(mid, max(1, int(in_channels * se_ratio))) if se_ratio > 0 else nn.Identity()
        self.project = nn.Sequential(nn.Conv2d(mid, out_channels, 1, bias=False), batch_norm(out_channels))
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        out = self.project(self.se(self.depthwise(self.expand(features))))
        return out + features if self.residual else out


class EfficientNetBackbone(nn.Module):
    """Stem + MBConv stages; ``forward`` returns the features of ``feature_stages``.

    Attributes ``feature_channels`` and ``feature_strides`` describe the returned list.
    """

    def __init__(
        self,
        *,
        in_channels: int,
        stem_channels: int,
        stages: Sequence[MBConvStage],
        feature_stages: Sequence[int],
        se_ratio: float,
    ) -> None:
        super().__init__()
        self.stem = ConvBnAct(in_channels, stem_channels, 3, stride=2)
        blocks = []
        channels, stride = stem_channels, 2
        self.feature_stages = tuple(feature_stages)
        feature_channels, feature_strides = [], []
        for index, stage in enumerate(stages):
            stage_blocks = []
            for repeat in range(stage.repeats):
                block_stride = stage.stride if repeat == 0 else 1
                stage_blocks.append(
                    MBConv(
                        channels,
                        stage.channels,
                        expand=stage.expand,
                        kernel=stage.kernel,
                        stride=block_stride,
                        se_ratio=se_ratio,
                    )
                )
                channels = stage.channels
            stride *= stage.stride
            blocks.append(nn.Sequential(*stage_blocks))
            if index in self.feature_stages:
                feature_channels.append(channels)
                feature_strides.append(stride)
        self.stages = nn.ModuleList(blocks)
        self.feature_channels: tuple[int, ...] = tuple(feature_channels)
        self.feature_strides: tuple[int, ...] = tuple(feature_strides)

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        """``(B, C_in, H, W)`` -> list of ``(B, C_s, ceil(H/s), ceil(W/s))`` for each feature stride."""
        features = self.stem(image)
        taps = []
        for index, stage in enumerate(self.stages):
            features = stage(features)
            if index in self.feature_stages:
                taps.append(features)
        return taps


def build_efficientnet(
    *,
    in_channels: int = 5,
    stages: Sequence[MBConvStage] = B0_STAGES,
    stem_channels: int = B0_STEM_CHANNELS,
    width_mult: float = 1.0,
    depth_mult: float = 1.0,
    se_ratio: float = 0.25,
    feature_stages: Sequence[int] = B0_FEATURE_STAGES,
) -> EfficientNetBackbone:
    """Build an MBConv backbone from a stage table.

    ``width_mult`` scales every channel count (rounded to multiples of 8), ``depth_mult`` every repeat
    count (``ceil``), as in EfficientNet's compound scaling.
    """
    if in_channels < 1:
        raise ValueError(f"in_channels must be >= 1, got {in_channels}")
    if width_mult <= 0:
        raise ValueError(f"width_mult must be > 0, got {width_mult}")
    if depth_mult <= 0:
        raise ValueError(f"depth_mult must be > 0, got {depth_mult}")
    if not 0 <= se_ratio <= 1:
        raise ValueError(f"se_ratio must be in [0, 1], got {se_ratio}")
    if not stages:
        raise ValueError("stages must not be empty")
    if sorted(set(feature_stages)) != list(feature_stages) or not all(
        0 <= i < len(stages) for i in feature_stages
    ):
        raise ValueError(
            f"feature_stages must be increasing indices into stages, got {tuple(feature_stages)}"
        )
    scaled = tuple(
        replace(
            stage,
            channels=make_divisible(stage.channels * width_mult),
            repeats=max(1, math.ceil(stage.repeats * depth_mult)),
        )
        for stage in stages
    )
    return EfficientNetBackbone(
        in_channels=in_channels,
        stem_channels=make_divisible(stem_channels * width_mult),
        stages=scaled,
        feature_stages=feature_stages,
        se_ratio=se_ratio,
    )
