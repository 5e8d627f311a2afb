"""Registered baseline builders: ``create_model("unet" | "tmvanet" | "smvanet" | "*_tiny", ...)``.

Classes come from the radar preset (background included), as for our own models. Tiny variants keep
the architecture and shrink the widths, for tests.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

from models.baselines.mvnet import MVRSS_WIDTH, MultiViewNet
from models.baselines.unet import CLASSIC_WIDTHS, UNet
from models.channel_surgery import apply_channel_table
from models.registry import register_model
from radar.profiles import RadarProfile, get_profile

Channels = dict[str, list[int]] | None  # per-layer widths of a slimmed network (models.slimming.prune)

TINY_UNET_WIDTHS = (4, 8, 16, 32, 64)
TINY_MV_WIDTH = 8


def _narrowed(model: nn.Module, channels: Channels) -> nn.Module:
    if channels:
        apply_channel_table(model, channels)
    return model


@register_model("unet")
def build_unet(*, preset: str | RadarProfile = "small", view: str = "ra",
               widths: Sequence[int] = CLASSIC_WIDTHS, channels: Channels = None) -> UNet:
    """Classic U-Net on one view (``"ra"`` or ``"rd"``), single frame. 31.04 M params at 4 classes."""
    return _narrowed(UNet(num_classes=get_profile(preset).num_classes, view=view, widths=tuple(widths)), channels)


@register_model("unet_tiny")
def build_unet_tiny(*, preset: str | RadarProfile = "small", view: str = "ra", channels: Channels = None) -> UNet:
    return build_unet(preset=preset, view=view, widths=TINY_UNET_WIDTHS, channels=channels)


@register_model("tmvanet")
def build_tmvanet(*, preset: str | RadarProfile = "small", width: int = MVRSS_WIDTH,
                  channels: Channels = None) -> MultiViewNet:
    """TMVA-Net: 5 frames, 3-D conv encoders. 5,630,984 params at 4 classes."""
    return _narrowed(MultiViewNet(num_classes=get_profile(preset).num_classes, temporal=True, width=width), channels)


@register_model("tmvanet_tiny")
def build_tmvanet_tiny(*, preset: str | RadarProfile = "small", channels: Channels = None) -> MultiViewNet:
    return build_tmvanet(preset=preset, width=TINY_MV_WIDTH, channels=channels)


@register_model("smvanet")
def build_smvanet(*, preset: str | RadarProfile = "small", width: int = MVRSS_WIDTH,
                  channels: Channels = None) -> MultiViewNet:
    """SMVA-Net: TMVA-Net on a single frame (2-D double conv encoders). 4,739,336 params at 4 classes."""
    return _narrowed(MultiViewNet(num_classes=get_profile(preset).num_classes, temporal=False, n_frames=1,
                                  width=width), channels)


@register_model("smvanet_tiny")
def build_smvanet_tiny(*, preset: str | RadarProfile = "small", channels: Channels = None) -> MultiViewNet:
    return build_smvanet(preset=preset, width=TINY_MV_WIDTH, channels=channels)
