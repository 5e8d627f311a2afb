"""Blocks shared by the 2-D baselines (U-Net, TMVA-Net, SMVA-Net).

All blocks work on feature maps ``(B, C, H, W)`` (``(B, C, T, H, W)`` for the 3-D one) and keep the
spatial size (``padding = dilation * (k // 2)``).
"""

from __future__ import annotations

from torch import nn


class ConvBnReLU(nn.Sequential):
    """Conv2d (no bias) -> BatchNorm2d -> ReLU, the classic U-Net unit. ``(B, C_in, H, W) -> (B, C_out, H, W)``."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3) -> None:
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )


class ConvBnLeaky(nn.Sequential):
    """Conv2d (with bias) -> BatchNorm2d -> LeakyReLU(0.01), MVRSS's unit (its biases count in the
    parameter totals). ``(B, C_in, H, W) -> (B, C_out, H, W)``; ``dilation`` widens a 3x3 for ASPP."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 1, *, dilation: int = 1) -> None:
        super().__init__(
            nn.Conv2d(in_channels, out_channels, kernel_size, padding=dilation * (kernel_size // 2), dilation=dilation),
            nn.BatchNorm2d(out_channels),
            nn.LeakyReLU(inplace=True),
        )


def double_conv_leaky(in_channels: int, out_channels: int) -> nn.Sequential:
    """Two 3x3 :class:`ConvBnLeaky`. ``(B, C_in, H, W) -> (B, C_out, H, W)``."""
    return nn.Sequential(ConvBnLeaky(in_channels, out_channels, 3), ConvBnLeaky(out_channels, out_channels, 3))


class TemporalDoubleConv(nn.Sequential):
    """Two (Conv3d 3x3x3 with bias -> BatchNorm3d -> LeakyReLU), no padding along time.

    ``(B, C_in, T, H, W) -> (B, C_out, T - 4, H, W)``: with ``T = 5`` frames the time axis is consumed.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        layers: list[nn.Module] = []
        for c_in in (in_channels, out_channels):
            layers += [nn.Conv3d(c_in, out_channels, 3, padding=(0, 1, 1)), nn.BatchNorm3d(out_channels),
                       nn.LeakyReLU(inplace=True)]
        super().__init__(*layers)
