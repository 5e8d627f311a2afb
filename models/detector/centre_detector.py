"""Stage 1 of ERASE-Net: the centre detector (docs/design.md section 5) and its registered builders.

Input: normalised log power with Doppler as channels, ``(B, D, R, A)``. A 1x1 conv compresses the
``D`` Doppler channels to 3 (the paper's; ``doppler_channels`` widens it); two channels with each RA cell's
Cartesian (x, y), divided by the largest range so they lie in [-1, 1] and [0, 1], are appended: 5 channels go
into the backbone.
Backbone (MBConv, strides 4..32) -> BiFPN neck (P3..P7, fused down to stride 4) -> CenterNet heads.
Outputs are on the stride-4 grid ``(ceil(R / 4), ceil(A / 4))`` (dict, see :class:`CentreNetHead`).

Any ``(R, A)`` works: the input is zero-padded to a multiple of ``pad_multiple`` (4 by default, so
output cell ``i`` covers input bins ``4i .. 4i+3`` on every axis) and the outputs are cropped back;
the backbone and BiFPN handle sizes that are not multiples of 32 or 128 themselves (every level is
``ceil`` of the one above and upsampling targets the exact size), which costs fewer MACs than padding
424 x 512 up to 512 x 512.

Registered models (``models.registry.create_model``):

- ``centre_detector``: ``variant`` one of :data:`VARIANTS` (default :data:`SMALLER_VARIANT`), width
  and depth multipliers, neck and head widths;
- ``centre_detector_tiny``: the same builder with widths x0.25, one block per stage, a 1-layer
  16-channel BiFPN and 16-channel heads, for tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from models.capabilities import InputShapes, Stage
from models.channel_surgery import apply_channel_table
from models.detector.bifpn import BiFPNNeck
from models.detector.centernet import CentreNetHead
from models.detector.efficientnet import (
    B0_STAGES,
    EfficientNetBackbone,
    MBConvStage,
    build_efficientnet,
    smaller_stages,
)
from models.detector.targets import CentreTargets
from models.layers import require_at_least
from models.registry import register_model
from radar.profiles import RadarProfile, get_profile

COMPRESSED_DOPPLER_CHANNELS = 3
CARTESIAN_CHANNELS = 2


@dataclass(frozen=True)
class DetectorVariant:
    """A reading of the paper's "smaller" EfficientNet: a stage table and the head conv type."""

    stages: tuple[MBConvStage, ...]
    separable_heads: bool
    description: str


VARIANTS: dict[str, DetectorVariant] = {
    "b0": DetectorVariant(B0_STAGES, False, "plain EfficientNet-B0 stages, dense 3x3 heads"),
    "slim": DetectorVariant(
        smaller_stages(), False, "last three stages x2/3 channels, repeats unchanged, dense 3x3 heads"
    ),
    "slim_sep": DetectorVariant(
        smaller_stages(), True, "last three stages x2/3 channels, repeats unchanged, separable 3x3 heads"
    ),
    "literal": DetectorVariant(
        smaller_stages(fewer_repeats=(3, 4, 5)),
        False,
        "last three stages x2/3 channels and stages 4-6 one repeat fewer, dense 3x3 heads",
    ),
    "literal_sep": DetectorVariant(
        smaller_stages(fewer_repeats=(3, 4, 5)),
        True,
        "last three stages x2/3 channels and stages 4-6 one repeat fewer, separable 3x3 heads",
    ),
}
# Closest to the paper's 2.08 M params / 0.49 GMACs at 256 x 256 (figures in efficientnet.py).
SMALLER_VARIANT = "slim_sep"


def normalised_cartesian(x: np.ndarray, y: np.ndarray) -> torch.Tensor:
    """Cartesian channels ``(2, R, A)`` float32 from per-cell ``x, y`` in metres ``(R, A)``.

    Both are divided by the largest range on the grid, so x lies in [-1, 1] and y in [0, 1].
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2:
        raise ValueError(f"cartesian x and y must both be (R, A), got {x.shape} and {y.shape}")
    scale = float(np.hypot(x, y).max())
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError("cartesian x, y must be finite and not all zero")
    return torch.from_numpy(np.stack([x, y]) / scale).float()


class CentreDetector(nn.Module):
    """Doppler 1x1 conv + Cartesian channels -> backbone -> neck -> head.

    ``backbone(image (B, 5, R', A')) -> list of 4 features`` (strides 4, 8, 16, 32, with a
    ``feature_channels`` attribute), ``neck(features) -> (B, C, ceil(R'/4), ceil(A'/4))`` and ``head``
    a :class:`CentreNetHead`; defaults (the chosen smaller variant, BiFPN D0) are built
    for any of them given as ``None``. ``cartesian``: ``(x, y)`` in metres, each ``(R, A)``.

    In training mode a batch of 1 at 128 x 128 fails in BatchNorm: P7 is then 1 x 1 (one value per
    channel). Train with batches of 2 or more there.
    """

    stage: ClassVar[Stage] = Stage.DETECTOR
    channel_tracer: ClassVar[str] = "detector"

    def dense_input_shapes(self, profile: RadarProfile) -> InputShapes:
        """One frame's log power as the detector reads it: ``((1, D, R, A),)``."""
        return ((1, profile.n_doppler, profile.n_range, profile.n_angle),)

    def __init__(
        self,
        *,
        doppler_bins: int,
        cartesian: tuple[np.ndarray, np.ndarray],
        backbone: nn.Module | None = None,
        neck: nn.Module | None = None,
        head: CentreNetHead | None = None,
        pad_multiple: int = 4,
        doppler_channels: int = COMPRESSED_DOPPLER_CHANNELS,
        history_frames: int = 0,
    ) -> None:
        super().__init__()
        require_at_least(1, doppler_bins=doppler_bins, doppler_channels=doppler_channels)
        require_at_least(0, history_frames=history_frames)
        if pad_multiple < 1 or pad_multiple % 4:
            raise ValueError(
                f"pad_multiple must be a positive multiple of the output stride 4, got {pad_multiple}"
            )
        self.doppler_compress = nn.Conv2d(doppler_bins, doppler_channels, 1)
        self.register_buffer("cartesian", normalised_cartesian(*cartesian)[None], persistent=False)
        self.history_frames = history_frames
        in_channels = backbone_in_channels(doppler_channels, history_frames)
        self.backbone = (
            backbone
            if backbone is not None
            else build_efficientnet(in_channels=in_channels, stages=VARIANTS[SMALLER_VARIANT].stages)
        )
        self.neck = neck if neck is not None else BiFPNNeck(self.backbone.feature_channels)
        self.head = (
            head
            if head is not None
            else CentreNetHead(
                doppler_bins=doppler_bins,
                in_channels=getattr(self.neck, "out_channels", 64),
                separable=VARIANTS[SMALLER_VARIANT].separable_heads,
            )
        )
        self.doppler_bins = doppler_bins
        self.pad_multiple = pad_multiple
        self.output_stride = 4

    @property
    def grid_shape(self) -> tuple[int, int]:
        """The ``(R, A)`` grid this detector's Cartesian channels were built for."""
        return tuple(self.cartesian.shape[-2:])

    def forward(self, log_power: torch.Tensor, history: torch.Tensor | None = None,
                history_present: torch.Tensor | None = None,
                window_origins: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """``(B, D, R, A)`` normalised log power -> dict of ``(B, ., ceil(R/4), ceil(A/4))`` outputs.

        With ``history_frames`` H > 0, ``history`` (B, H, D, R, A) holds the earlier frames of the sequence
        (normalised alike, the latest first) and ``history_present`` (B, H) which of them exist (default all);
        without ``history`` every earlier frame counts as absent, so a single cube runs as it is.

        ``window_origins`` (B, 2) int: the inputs are range x angle windows of the frame (crop training), of any
        size up to the grid, starting at these (range, angle) bins, multiples of the output stride; each window
        reads the Cartesian channels of its own place on the grid. None: the inputs are whole frames.
        """
        self._check_input(log_power, window_origins)
        batch, _, n_range, n_angle = log_power.shape
        cartesian = (self.cartesian.expand(batch, -1, -1, -1) if window_origins is None
                     else torch.cat([self.cartesian[..., r:r + n_range, a:a + n_angle]
                                     for r, a in window_origins.tolist()]))  # (B, 2, R, A)
        image = torch.cat(
            [self.doppler_compress(log_power), cartesian,
             *self._history_channels(log_power, history, history_present)], dim=1
        )  # (B, C + 2 [+ H (C + 1)], R, A)
        if self.history_frames and history is None:
            # a single cube: every earlier frame is absent, so all its channels are zero; padded rather than built,
            # so that an exported graph carries no constant block of zeros (H (C + 1) x R x A floats)
            image = F.pad(image, (0, 0, 0, 0, 0, self.history_frames * (self.doppler_compress.out_channels + 1)))
        pad_range = -n_range % self.pad_multiple
        pad_angle = -n_angle % self.pad_multiple
        if pad_range or pad_angle:
            image = F.pad(image, (0, pad_angle, 0, pad_range))
        outputs = self.head(self.neck(self.backbone(image)))
        out_range = -(-n_range // self.output_stride)
        out_angle = -(-n_angle // self.output_stride)
        return {name: value[..., :out_range, :out_angle] for name, value in outputs.items()}

    def _check_input(self, log_power: torch.Tensor, window_origins: torch.Tensor | None) -> None:
        grid_range, grid_angle = self.grid_shape
        if log_power.ndim != 4 or log_power.shape[1] != self.doppler_bins or (
                window_origins is None and tuple(log_power.shape[-2:]) != self.grid_shape):
            raise ValueError(f"expected log power (B, {self.doppler_bins}, {grid_range}, {grid_angle}), "
                             f"got {tuple(log_power.shape)}")
        if window_origins is None:
            return
        n_range, n_angle = log_power.shape[-2:]
        if tuple(window_origins.shape) != (log_power.shape[0], 2):
            raise ValueError(f"window_origins must be (B, 2) = ({log_power.shape[0]}, 2) (range, angle) bins, got "
                             f"{tuple(window_origins.shape)}")
        for r, a in window_origins.tolist():
            if r % self.output_stride or a % self.output_stride or not (
                    0 <= r <= grid_range - n_range and 0 <= a <= grid_angle - n_angle):
                raise ValueError(f"a {n_range} x {n_angle} window at bins ({r}, {a}) must start on a multiple of "
                                 f"{self.output_stride} and fit the {grid_range} x {grid_angle} grid")

    def _history_channels(self, log_power: torch.Tensor, history: torch.Tensor | None,
                          history_present: torch.Tensor | None) -> list[torch.Tensor]:
        """Each earlier frame compressed by the same 1x1 conv (zero where absent), then one presence channel
        per earlier frame: ``[]`` for a single-frame detector, and without ``history`` (:meth:`forward` pads the
        zeros then)."""
        if not self.history_frames:
            if history is not None:
                raise ValueError("this detector reads one frame (history_frames 0): give no history")
            return []
        if history is None:
            return []
        batch, _, n_range, n_angle = log_power.shape
        n_history = self.history_frames
        expected = (batch, n_history, self.doppler_bins, n_range, n_angle)
        if tuple(history.shape) != expected:
            raise ValueError(f"expected history {expected} (B, H, D, R, A), got {tuple(history.shape)}")
        present = (log_power.new_ones(batch, n_history) if history_present is None
                   else history_present.to(log_power.dtype))
        compressed = self.doppler_compress(history.flatten(0, 1)).unflatten(0, (batch, n_history))
        compressed = (compressed * present[:, :, None, None, None]).flatten(1, 2)
        return [compressed, present[:, :, None, None].expand(-1, -1, n_range, n_angle)]

    def compute_loss(
        self, outputs: dict[str, torch.Tensor], targets: CentreTargets
    ) -> dict[str, torch.Tensor]:
        """Named losses, see :meth:`CentreNetHead.compute_loss`."""
        return self.head.compute_loss(outputs, targets)

    def decode(
        self, outputs: dict[str, torch.Tensor], k: int = 100, score_threshold: float = 0.1
    ) -> list[dict[str, torch.Tensor]]:
        """Centres per frame in input bins, see :meth:`CentreNetHead.decode`."""
        return self.head.decode(outputs, k=k, score_threshold=score_threshold)


def backbone_in_channels(doppler_channels: int, history_frames: int = 0) -> int:
    """The backbone's input channels: the compressed Doppler and the Cartesian (x, y), then per earlier frame
    its compressed Doppler and a presence channel."""
    return doppler_channels + CARTESIAN_CHANNELS + history_frames * (doppler_channels + 1)


def _resolve_grid(
    preset: str | RadarProfile, cartesian: tuple[np.ndarray, np.ndarray] | None
) -> tuple[int, tuple[np.ndarray, np.ndarray]]:
    profile = get_profile(preset)
    if cartesian is None:
        cartesian = profile.ra_cartesian
    elif np.shape(cartesian[0]) != (profile.n_range, profile.n_angle):
        raise ValueError(
            f"cartesian grids must be (R, A) = {(profile.n_range, profile.n_angle)} for preset "
            f"{profile.name!r}, got {np.shape(cartesian[0])}"
        )
    return profile.n_doppler, cartesian


@register_model("centre_detector")
def build_centre_detector(
    *,
    preset: str | RadarProfile = "small",
    variant: str = SMALLER_VARIANT,
    width_mult: float = 1.0,
    depth_mult: float = 1.0,
    neck_channels: int = 64,
    neck_layers: int = 3,
    head_channels: int = 64,
    separable_heads: bool | None = None,
    stages: Sequence[MBConvStage] | None = None,
    cartesian: tuple[np.ndarray, np.ndarray] | None = None,
    channels: dict[str, list[int]] | None = None,
    doppler_channels: int = COMPRESSED_DOPPLER_CHANNELS,
    heatmap_classes: int = 1,
    history_frames: int = 0,
) -> CentreDetector:
    """Centre detector for a radar preset.

    ``doppler_channels``: width of the 1x1 Doppler compression (the paper's 3); ``heatmap_classes``: 1 (one
    heatmap for every class, the paper's) or the preset's number of foreground classes (a heatmap per class);
    ``history_frames``: earlier frames of the sequence read beside the current one (0: one frame, the paper's).

    ``variant`` picks the stage table and head conv type from :data:`VARIANTS`; ``stages`` and
    ``separable_heads`` override them. ``cartesian`` (x, y metres, each (R, A)) defaults to the
    preset's RA grid. ``channels``: the per-layer widths of a slimmed detector
    (:func:`models.channel_surgery.apply_channel_table`), None for the full widths.
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {sorted(VARIANTS)}, got {variant!r}")
    for name, value in (
        ("neck_channels", neck_channels),
        ("neck_layers", neck_layers),
        ("head_channels", head_channels),
    ):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    chosen = VARIANTS[variant]
    doppler_bins, cartesian = _resolve_grid(preset, cartesian)
    backbone: EfficientNetBackbone = build_efficientnet(
        in_channels=backbone_in_channels(doppler_channels, history_frames),
        stages=chosen.stages if stages is None else tuple(stages),
        width_mult=width_mult,
        depth_mult=depth_mult,
    )
    neck = BiFPNNeck(backbone.feature_channels, channels=neck_channels, num_layers=neck_layers)
    head = CentreNetHead(
        doppler_bins=doppler_bins,
        in_channels=neck_channels,
        head_channels=head_channels,
        separable=chosen.separable_heads if separable_heads is None else separable_heads,
        heatmap_classes=heatmap_classes,
    )
    detector = CentreDetector(
        doppler_bins=doppler_bins, cartesian=cartesian, backbone=backbone, neck=neck, head=head,
        doppler_channels=doppler_channels, history_frames=history_frames,
    )
    if channels:
        apply_channel_table(detector, channels)
    return detector


@register_model("centre_detector_tiny")
def build_centre_detector_tiny(
    *,
    preset: str | RadarProfile = "small",
    variant: str = SMALLER_VARIANT,
    channels: dict[str, list[int]] | None = None,
    doppler_channels: int = COMPRESSED_DOPPLER_CHANNELS,
    heatmap_classes: int = 1,
    history_frames: int = 0,
) -> CentreDetector:
    """A 67 k-parameter detector with the real structure (every stage, BiFPN, three heads), for tests."""
    return build_centre_detector(
        preset=preset,
        variant=variant,
        doppler_channels=doppler_channels,
        heatmap_classes=heatmap_classes,
        history_frames=history_frames,
        width_mult=0.25,
        depth_mult=0.25,
        neck_channels=16,
        neck_layers=1,
        head_channels=16,
        channels=channels,
    )
