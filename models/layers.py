"""Small building blocks shared by the dense networks: conv-norm-activation, separable conv, SE.

Every block here works on feature maps ``(B, C, H, W)``; spatial sizes follow PyTorch's ``padding =
k // 2`` convention, so a stride-2 layer maps ``H`` to ``ceil(H / 2)`` and output cell ``i`` is centred
on input cell ``2 i`` (the detector's decoding relies on this).

BatchNorm defaults follow EfficientNet (TF momentum 0.99, i.e. PyTorch momentum 0.01, eps 1e-3).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

BN_MOMENTUM = 0.01
BN_EPS = 1e-3

_ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "silu": lambda: nn.SiLU(inplace=True),
    "relu": lambda: nn.ReLU(inplace=True),
    "sigmoid": nn.Sigmoid,
    "identity": nn.Identity,
}


def require_at_least(minimum: int, **values: int) -> None:
    """ValueError naming the first of ``values`` (an argument's name and value) below ``minimum``."""
    for name, value in values.items():
        if value < minimum:
            raise ValueError(f"{name} must be >= {minimum}, got {value}")


def make_activation(name: str) -> nn.Module:
    """A fresh activation module by name: ``silu``, ``relu``, ``sigmoid`` or ``identity``."""
    try:
        return _ACTIVATIONS[name]()
    except KeyError:
        raise ValueError(f"activation must be one of {sorted(_ACTIVATIONS)}, got {name!r}") from None


def make_divisible(channels: float, divisor: int = 8, min_value: int | None = None) -> int:
    """Round a channel count to a multiple of ``divisor`` (never more than 10% below ``channels``).

    The rule timm and the EfficientNet reference use when scaling widths.
    """
    min_value = min_value or divisor
    rounded = max(min_value, int(channels + divisor / 2) // divisor * divisor)
    if rounded < 0.9 * channels:
        rounded += divisor
    return int(rounded)


def batch_norm(channels: int, *, momentum: float = BN_MOMENTUM, eps: float = BN_EPS) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, momentum=momentum, eps=eps)


class ConvBnAct(nn.Sequential):
    """Conv2d (no bias) -> BatchNorm2d -> activation. ``(B, C_in, H, W) -> (B, C_out, H/s, W/s)``."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 1,
        *,
        stride: int = 1,
        groups: int = 1,
        act: str = "silu",
        bn_momentum: float = BN_MOMENTUM,
        bn_eps: float = BN_EPS,
    ) -> None:
        super().__init__(
            nn.Conv2d(
                in_channels,
                out_channels,
                kernel_size,
                stride=stride,
                padding=kernel_size // 2,
                groups=groups,
                bias=False,
            ),
            batch_norm(out_channels, momentum=bn_momentum, eps=bn_eps),
            make_activation(act),
        )
        self.in_channels = in_channels
        self.out_channels = out_channels


class SeparableConv2d(nn.Module):
    """Depthwise ``k x k`` conv then pointwise 1x1 conv, optionally BN and activation after.

    ``(B, C_in, H, W) -> (B, C_out, H, W)``. With ``norm=False`` the pointwise conv carries a bias
    (the form used in prediction heads).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        *,
        norm: bool = True,
        act: str = "identity",
    ) -> None:
        super().__init__()
        self.depthwise = nn.Conv2d(
            in_channels, in_channels, kernel_size, padding=kernel_size // 2, groups=in_channels, bias=False
        )
        self.pointwise = nn.Conv2d(in_channels, out_channels, 1, bias=not norm)
        self.norm = batch_norm(out_channels) if norm else nn.Identity()
        self.act = make_activation(act)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.act(self.norm(self.pointwise(self.depthwise(features))))


class SqueezeExcite(nn.Module):
    """Squeeze-and-excitation: global mean -> 1x1 reduce -> SiLU -> 1x1 expand -> sigmoid gate.

    ``(B, C, H, W) -> (B, C, H, W)``; ``se_channels`` is the bottleneck width (EfficientNet uses
    ``max(1, int(block_in * 0.25))`` with ``block_in`` the block's input, not its expanded width).
    """

    def __init__(self, channels: int, se_channels: int, *, act: str = "silu") -> None:
        super().__init__()
        if se_channels < 1:
            raise ValueError(f"se_channels must be >= 1, got {se_channels}")
        self.reduce = nn.Conv2d(channels, se_channels, 1)
        self.act = make_activation(act)
        self.expand = nn.Conv2d(se_channels, channels, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        gate = features.mean(dim=(2, 3), keepdim=True)  # (B, C, 1, 1)
        gate = self.expand(self.act(self.reduce(gate)))
        return features * torch.sigmoid(gate)
