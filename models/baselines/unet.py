"""The classic U-Net (Ronneberger et al.), one network per radar view (docs/design.md section 9).

Widths 64..1024 (four 2x max-pool downsamplings, four 2x2 stride-2 transposed-conv upsamplings, skip
concatenation, double 3x3 conv-BN-ReLU everywhere, 1x1 classifier): 31.04 M parameters, as quoted by
the paper. A view is one single-frame 2-D map: RA ``(R, A)`` (log power max over Doppler) or RD
``(R, D)`` (log of the power summed over angle). Sizes that do not halve evenly are handled by padding
the upsampled map to its skip connection, so any ``H, W >= 16`` works.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from models.baselines.blocks import ConvBnReLU
from models.capabilities import InputShapes, Stage

CLASSIC_WIDTHS = (64, 128, 256, 512, 1024)
UNET_VIEWS = ("ra", "rd")


def _double_conv(in_channels: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(ConvBnReLU(in_channels, out_channels), ConvBnReLU(out_channels, out_channels))


class UpStage(nn.Module):
    """2x2 stride-2 transposed conv (C -> C/2), pad to the skip, concatenate, double conv (C -> C_out).

    ``(B, C, H, W), skip (B, C/2, 2H', 2W') -> (B, C_out, 2H', 2W')``.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.up = nn.ConvTranspose2d(in_channels, in_channels // 2, 2, stride=2)
        self.conv = _double_conv(in_channels // 2 + out_channels, out_channels)

    def forward(self, features: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        up = self.up(features)
        dh, dw = skip.shape[-2] - up.shape[-2], skip.shape[-1] - up.shape[-1]
        if dh or dw:  # odd sizes lost a row/column when pooled
            up = F.pad(up, (dw // 2, dw - dw // 2, dh // 2, dh - dh // 2))
        return self.conv(torch.cat([skip, up], dim=1))


class UNet(nn.Module):
    """U-Net on one view. ``forward(view (B, C_in, H, W)) -> {view_name: logits (B, num_classes, H, W)}``.

    ``view`` names the output (``"ra"`` or ``"rd"``) so the multi-view losses and evaluation treat a
    U-Net like one branch of the multi-view networks.
    """

    stage: ClassVar[Stage] = Stage.BASELINE
    channel_tracer: ClassVar[str] = "unet"

    def dense_input_shapes(self, profile: Any) -> InputShapes:
        """Its one view: ``((1, 1, R, A),)`` or ``((1, 1, R, D),)``."""
        return ((1, 1, profile.n_range, profile.n_angle if self.view == "ra" else profile.n_doppler),)

    def __init__(self, *, num_classes: int, view: str = "ra", in_channels: int = 1,
                 widths: Sequence[int] = CLASSIC_WIDTHS) -> None:
        super().__init__()
        if view not in UNET_VIEWS:
            raise ValueError(f"view must be one of {UNET_VIEWS}, got {view!r}")
        widths = tuple(int(w) for w in widths)
        if len(widths) < 2 or any(w < 2 or w % 2 for w in widths):
            raise ValueError(f"widths must be >= 2 even channel counts, at least two of them, got {widths}")
        if num_classes < 2:
            raise ValueError(f"num_classes must be >= 2, got {num_classes}")
        self.view = view
        self.num_classes = num_classes
        self.n_frames = 1
        self.stem = _double_conv(in_channels, widths[0])
        pairs = list(zip(widths[:-1], widths[1:], strict=True))  # (64, 128), ..., (512, 1024)
        self.down = nn.ModuleList(_double_conv(c_in, c_out) for c_in, c_out in pairs)
        self.up = nn.ModuleList(UpStage(c_out, c_in) for c_in, c_out in reversed(pairs))
        self.classifier = nn.Conv2d(widths[0], num_classes, 1)

    @property
    def min_size(self) -> int:
        """Smallest H and W that survive the downsamplings."""
        return 2 ** len(self.down)

    def forward(self, view: torch.Tensor) -> dict[str, torch.Tensor]:
        if view.ndim != 4 or min(view.shape[-2:]) < self.min_size:
            raise ValueError(f"expected a view (B, C, H, W) with H, W >= {self.min_size}, got {tuple(view.shape)}")
        skips = [self.stem(view)]  # (B, 64, H, W)
        for stage in self.down:
            skips.append(stage(F.max_pool2d(skips[-1], 2)))
        features = skips.pop()  # (B, 1024, H/16, W/16)
        for stage in self.up:
            features = stage(features, skips.pop())
        return {self.view: self.classifier(features)}  # (B, num_classes, H, W)
