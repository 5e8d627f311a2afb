"""BiFPN neck (EfficientDet-D0: 64 channels, 3 layers) and the fusion down to output stride 4.

Levels P3..P7 have strides 8..128. P3-P5 come from the backbone's stride 8/16/32 features through a
1x1 conv + BN; P6 = max-pool(1x1 conv + BN of C5), P7 = max-pool(P6). Each BiFPN layer runs the
top-down then the bottom-up path; every node is fast normalised fusion (ReLU'd learnable weights,
``w_i / (sum w + 1e-4)``) -> SiLU -> separable 3x3 conv + BN.

Sizes need not be powers of two: each level is ``ceil`` of the one above (stride-2 convs and max-pools
with ``padding = k // 2``), upsampling goes to the exact size of the target level, so any input size
works without padding to a multiple of 128.

:class:`BiFPNNeck` adds one more top-down node that brings P3 to stride 4 by fusing it with the
backbone's stride-4 feature (C2), since the CenterNet heads work at stride 4 (docs/design.md section 5). As only
P3 feeds that node, the last BiFPN layer keeps its top-down path only.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from models.layers import SeparableConv2d, batch_norm

FUSION_EPS = 1e-4


def _project(in_channels: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 1, bias=False), batch_norm(out_channels))


def _upsample_to(features: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    return F.interpolate(features, size=reference.shape[-2:], mode="nearest")


def _downsample(features: torch.Tensor) -> torch.Tensor:
    return F.max_pool2d(features, kernel_size=3, stride=2, padding=1)  # H -> ceil(H / 2)


class FusionNode(nn.Module):
    """Fast normalised fusion of ``num_inputs`` same-shape maps, then SiLU and a separable conv.

    ``[(B, C, H, W)] * n -> (B, C, H, W)``.
    """

    def __init__(self, channels: int, num_inputs: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(num_inputs))
        self.act = nn.SiLU()
        self.conv = SeparableConv2d(channels, channels, 3, norm=True)

    def forward(self, inputs: Sequence[torch.Tensor]) -> torch.Tensor:
        weight = F.relu(self.weight)
        weight = weight / (weight.sum() + FUSION_EPS)
        fused = sum(w * x for w, x in zip(weight, inputs, strict=True))
        return self.conv(self.act(fused))


class BiFPNLayer(nn.Module):
    """One bidirectional layer over P3..P7: ``list of 5 (B, C, H_l, W_l) -> same shapes``.

    With ``bottom_up=False`` only the top-down path is built and only ``[P3]`` is returned (the last
    layer of a neck that uses P3 alone: a bottom-up path there would feed nothing).
    """

    def __init__(self, channels: int, num_levels: int = 5, *, bottom_up: bool = True) -> None:
        super().__init__()
        if num_levels < 2:
            raise ValueError(f"num_levels must be >= 2, got {num_levels}")
        self.num_levels = num_levels
        # top-down nodes for levels num_levels-2 .. 0; bottom-up nodes for levels 1 .. num_levels-1
        self.top_down = nn.ModuleList(FusionNode(channels, 2) for _ in range(num_levels - 1))
        self.bottom_up = nn.ModuleList(
            FusionNode(channels, 3 if level < num_levels - 1 else 2)
            for level in (range(1, num_levels) if bottom_up else ())
        )

    def forward(self, levels: list[torch.Tensor]) -> list[torch.Tensor]:
        n = self.num_levels
        top_down = [None] * n
        top_down[n - 1] = levels[n - 1]
        for i, level in enumerate(range(n - 2, -1, -1)):
            top_down[level] = self.top_down[i](
                [levels[level], _upsample_to(top_down[level + 1], levels[level])]
            )
        out = [top_down[0]]
        if not self.bottom_up:
            return out
        for i, level in enumerate(range(1, n)):
            below = _downsample(out[-1])
            if level < n - 1:
                out.append(self.bottom_up[i]([levels[level], top_down[level], below]))
            else:
                out.append(self.bottom_up[i]([levels[level], below]))
        return out


class BiFPN(nn.Module):
    """Input projections + ``num_layers`` BiFPN layers.

    ``forward([C3, C4, C5])`` with ``C_l`` of shape ``(B, in_channels[l], H_l, W_l)`` returns
    ``[P3, ..., P7]``, each ``(B, channels, ., .)``; with ``p3_only`` just ``[P3]`` (the last layer's
    bottom-up path is then not built).
    """

    def __init__(
        self, in_channels: Sequence[int], *, channels: int = 64, num_layers: int = 3, p3_only: bool = False
    ) -> None:
        super().__init__()
        if len(in_channels) != 3:
            raise ValueError(f"in_channels must give C3, C4, C5 (3 values), got {tuple(in_channels)}")
        if channels < 1:
            raise ValueError(f"channels must be >= 1, got {channels}")
        if num_layers < 1:
            raise ValueError(f"num_layers must be >= 1, got {num_layers}")
        self.lateral = nn.ModuleList(_project(c, channels) for c in in_channels)
        self.p6_project = _project(in_channels[-1], channels)
        self.layers = nn.ModuleList(
            BiFPNLayer(channels, 5, bottom_up=not (p3_only and i == num_layers - 1))
            for i in range(num_layers)
        )
        self.channels = channels

    def forward(self, features: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        levels = [lateral(c) for lateral, c in zip(self.lateral, features, strict=True)]
        p6 = _downsample(self.p6_project(features[-1]))
        levels += [p6, _downsample(p6)]
        for layer in self.layers:
            levels = layer(levels)
        return levels


class BiFPNNeck(nn.Module):
    """BiFPN over C3..C5 plus a stride-4 node fusing P3 (upsampled) with the projected C2.

    ``forward([C2, C3, C4, C5])`` (strides 4, 8, 16, 32) -> ``(B, channels, ceil(H/4), ceil(W/4))``.
    """

    def __init__(self, in_channels: Sequence[int], *, channels: int = 64, num_layers: int = 3) -> None:
        super().__init__()
        if len(in_channels) != 4:
            raise ValueError(f"in_channels must give C2, C3, C4, C5 (4 values), got {tuple(in_channels)}")
        self.bifpn = BiFPN(in_channels[1:], channels=channels, num_layers=num_layers, p3_only=True)
        self.c2_project = _project(in_channels[0], channels)
        self.stride4 = FusionNode(channels, 2)
        self.out_channels = channels
        self.output_stride = 4

    def forward(self, features: Sequence[torch.Tensor]) -> torch.Tensor:
        c2 = self.c2_project(features[0])
        p3 = self.bifpn(features[1:])[0]
        return self.stride4([c2, _upsample_to(p3, c2)])
