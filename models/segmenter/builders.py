"""Registered segmenter builders: ``create_model("minkunet" | "spvcnn" | "*_tiny", ...)``.

The number of classes comes from the radar preset (background included); widths come from a ratio of
the paper's base widths unless given explicitly; a slimmed network also stores its per-layer ``channels``
table (:mod:`models.slimming.prune`).
"""

from __future__ import annotations

from collections.abc import Sequence

from models.channel_surgery import apply_channel_table
from models.registry import register_model
from models.segmenter.minkunet import MinkUNet, scaled_widths
from models.segmenter.spvcnn import SPVCNN
from radar.profiles import RadarProfile, get_profile
from radar.roi import N_FEATURES

PAPER_RATIO = 0.37  # 2.92 M params with 4 features and 5 classes (the paper's 2.93 M)
TINY_RATIO = 0.1


def _build(cls: type[MinkUNet], preset: str | RadarProfile, ratio: float, widths: Sequence[int] | None,
           blocks_per_stage: int, channels: dict[str, list[int]] | None = None) -> MinkUNet:
    profile = get_profile(preset)
    model = cls(in_channels=N_FEATURES, num_classes=profile.num_classes,
                widths=tuple(widths) if widths is not None else scaled_widths(ratio),
                blocks_per_stage=blocks_per_stage)
    if channels:  # per-layer widths of a slimmed network (models.slimming.prune)
        apply_channel_table(model, channels)
    return model


@register_model("minkunet")
def build_minkunet(*, preset: str | RadarProfile = "small", ratio: float = PAPER_RATIO,
                   widths: Sequence[int] | None = None, blocks_per_stage: int = 2,
                   channels: dict[str, list[int]] | None = None) -> MinkUNet:
    return _build(MinkUNet, preset, ratio, widths, blocks_per_stage, channels)


@register_model("spvcnn")
def build_spvcnn(*, preset: str | RadarProfile = "small", ratio: float = PAPER_RATIO,
                 widths: Sequence[int] | None = None, blocks_per_stage: int = 2,
                 channels: dict[str, list[int]] | None = None) -> SPVCNN:
    return _build(SPVCNN, preset, ratio, widths, blocks_per_stage, channels)


@register_model("minkunet_tiny")
def build_minkunet_tiny(*, preset: str | RadarProfile = "small",
                        channels: dict[str, list[int]] | None = None) -> MinkUNet:
    return _build(MinkUNet, preset, TINY_RATIO, None, 1, channels)


@register_model("spvcnn_tiny")
def build_spvcnn_tiny(*, preset: str | RadarProfile = "small",
                      channels: dict[str, list[int]] | None = None) -> SPVCNN:
    return _build(SPVCNN, preset, TINY_RATIO, None, 1, channels)
