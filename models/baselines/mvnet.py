"""TMVA-Net and SMVA-Net (Ouaknine et al., "Multi-View Radar Semantic Segmentation", ICCV 2021).

Three views of a RAD cube go in, each as ``(B, T, H, W)`` with ``T`` frames, oldest first:

- RD ``(B, T, R, D)``, RA ``(B, T, R, A)``, AD ``(B, T, A, D)``;

two segmentations come out: ``{"rd": (B, C, R, D), "ra": (B, C, R, A)}`` (logits).

Per view an encoder (:class:`ViewEncoder`) turns the frames into 2-D features (TMVA-Net: two 3x3x3
convs 1 -> W with no temporal padding, consuming ``T = 5`` frames; SMVA-Net: a 2-D double conv on one
frame), halves the rows twice by max-pooling (the Doppler axis is never downsampled: it is padded by one
column and pooled with stride (2, 1)), with a double conv in between, and gives both the pooled features
and a 1x1 "latent" projection. An ASPP block (image pooling, 1x1, 3x3 at dilations 6/12/18; W channels
each) and a 1x1 conv 5W -> W summarise each view. The three latents are concatenated and fused by a 1x1
conv per decoder; each decoder (RD, RA) takes [its ASPP features, the fused latent, the AD ASPP
features] (3W channels), and upsamples twice by transposed convs ((2, 1) for RD, 2x2 for RA), each
followed by a double conv, then a 1x1 classifier. With ``W = 128`` and 4 classes this is exactly the
reference's TMVA-Net (5,630,984 parameters); SMVA-Net has 4,739,336.

Departures from the reference, none of which changes the parameters or, on square grids, the output:

- The reference's image pooling is a fixed 64x64 average pool followed by a bilinear resize (only valid
  for 256-bin inputs); here it is a global mean broadcast back, identical at 256 bins and valid for
  every preset.
- The reference concatenates the three views' feature maps as they are, which only works when they
  share one grid (R = A, as in CARRADA). When they do not (the ``nxp`` preset: 424 x 512), each
  decoder resizes the other views' features to its own grid (bilinear) before concatenating.
- CARRADA stores RA with range reversed, so the reference's coherence loss flips RD along range; in our
  frame both views have range bin 0 nearest and no flip is needed (see :mod:`models.baselines.losses`).

Weights are initialised as the reference does: Xavier-uniform for 2-D conv weights, zero biases, the
PyTorch defaults for everything else.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from models.baselines.blocks import ConvBnLeaky, TemporalDoubleConv, double_conv_leaky
from models.capabilities import InputShapes, Stage

MVRSS_WIDTH = 128
TEMPORAL_FRAMES = 5  # two unpadded 3x3x3 convs consume exactly five frames
ASPP_DILATIONS = (6, 12, 18)
VIEW_DOPPLER_COLUMNS = {"rd": True, "ra": False, "ad": True}  # views whose columns are Doppler bins


class ViewEncoder(nn.Module):
    """Encoder of one view. ``(B, T, H, W) -> features (B, W, H/4, W'), latent (B, W, H/4, W')``.

    ``W' = W`` when the columns are Doppler (never downsampled), ``W / 4`` otherwise.
    """

    def __init__(self, *, width: int, n_frames: int, temporal: bool, doppler_columns: bool) -> None:
        super().__init__()
        self.temporal = temporal
        self.doppler_columns = doppler_columns
        self.frames = TemporalDoubleConv(1, width) if temporal else double_conv_leaky(n_frames, width)
        self.conv = double_conv_leaky(width, width)
        self.latent = ConvBnLeaky(width, width, 1)

    def _downsample(self, features: torch.Tensor) -> torch.Tensor:
        if self.doppler_columns:  # pad one Doppler column, pool rows only: (H, D) -> (H/2, D)
            return F.max_pool2d(F.pad(features, (0, 1, 0, 0)), 2, stride=(2, 1))
        return F.max_pool2d(features, 2)

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.temporal:
            features = self.frames(frames[:, None]).squeeze(2)  # (B, 1, 5, H, W) -> (B, W, 1, H, W) -> (B, W, H, W)
        else:
            features = self.frames(frames)  # (B, W, H, W)
        features = self._downsample(self.conv(self._downsample(features)))  # (B, W, H/4, W')
        return features, self.latent(features)


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling. ``(B, C, H, W) -> (B, 5 * C_out, H, W)``.

    Branches in the reference's order: 1x1, 3x3 at each dilation, then image pooling (global mean
    broadcast back to ``H x W``, then a 1x1 conv with bias and no norm). The reference runs that 1x1 conv
    on the broadcast map rather than on the 1x1 mean: the result is the same constant, but it costs
    ``H * W * C * C_out`` MACs (0.2 G for TMVA-Net at 256 bins), which we keep so the MAC counts match
    the reference's.
    """

    def __init__(self, in_channels: int, out_channels: int, dilations: tuple[int, ...] = ASPP_DILATIONS) -> None:
        super().__init__()
        self.pool_conv = nn.Conv2d(in_channels, out_channels, 1)
        self.branches = nn.ModuleList(
            [ConvBnLeaky(in_channels, out_channels, 1)]
            + [ConvBnLeaky(in_channels, out_channels, 3, dilation=d) for d in dilations])

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        pooled = features.mean(dim=(2, 3), keepdim=True).expand_as(features)  # (B, C, H, W), constant
        pooled = self.pool_conv(pooled)  # (B, C_out, H, W)
        return torch.cat([branch(features) for branch in self.branches] + [pooled], dim=1)


class ViewDecoder(nn.Module):
    """Decoder of one output view. ``(B, 3W, H/4, W') -> logits (B, num_classes, H, W)``.

    Upsampling is (2, 1) along rows only for RD (Doppler columns), 2x2 for RA.
    """

    def __init__(self, *, width: int, num_classes: int, doppler_columns: bool) -> None:
        super().__init__()
        scale = (2, 1) if doppler_columns else (2, 2)
        self.up1 = nn.ConvTranspose2d(3 * width, width, scale, stride=scale)
        self.conv1 = double_conv_leaky(width, width)
        self.up2 = nn.ConvTranspose2d(width, width, scale, stride=scale)
        self.conv2 = double_conv_leaky(width, width)
        self.classifier = nn.Conv2d(width, num_classes, 1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.classifier(self.conv2(self.up2(self.conv1(self.up1(features)))))


def _to_grid(features: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Features resized to ``grid`` (bilinear); unchanged (no op at all) when already on it."""
    if tuple(features.shape[-2:]) == grid:
        return features
    return F.interpolate(features, size=grid, mode="bilinear", align_corners=False)


class MultiViewNet(nn.Module):
    """TMVA-Net (``temporal=True``, 5 frames) or SMVA-Net (``temporal=False``, ``n_frames`` frames as
    channels, 1 by default). ``forward(rd, ra, ad) -> {"rd": (B, C, R, D), "ra": (B, C, R, A)}``.

    Inputs ``(B, T, H, W)`` as in the module docstring; R and A must be multiples of 4.
    """

    stage: ClassVar[Stage] = Stage.BASELINE
    channel_tracer: ClassVar[str] = "multiview"

    def dense_input_shapes(self, profile: Any) -> InputShapes:
        """The three views of ``n_frames`` frames: ``((1, T, R, D), (1, T, R, A), (1, T, A, D))``."""
        t, r, a, d = self.n_frames, profile.n_range, profile.n_angle, profile.n_doppler
        return ((1, t, r, d), (1, t, r, a), (1, t, a, d))

    def __init__(self, *, num_classes: int, temporal: bool, n_frames: int | None = None,
                 width: int = MVRSS_WIDTH) -> None:
        super().__init__()
        n_frames = (TEMPORAL_FRAMES if temporal else 1) if n_frames is None else n_frames
        if temporal and n_frames != TEMPORAL_FRAMES:
            raise ValueError(f"n_frames must be {TEMPORAL_FRAMES} for the temporal (3-D conv) encoder, got {n_frames}")
        if n_frames < 1 or width < 1 or num_classes < 2:
            raise ValueError(f"need n_frames >= 1, width >= 1 and num_classes >= 2; got n_frames={n_frames}, "
                             f"width={width}, num_classes={num_classes}")
        self.num_classes = num_classes
        self.temporal = temporal
        self.n_frames = n_frames
        self.width = width
        self.encoders = nn.ModuleDict({
            view: ViewEncoder(width=width, n_frames=n_frames, temporal=temporal, doppler_columns=doppler)
            for view, doppler in VIEW_DOPPLER_COLUMNS.items()})
        self.aspp = nn.ModuleDict({view: ASPP(width, width) for view in VIEW_DOPPLER_COLUMNS})
        self.aspp_fuse = nn.ModuleDict({view: ConvBnLeaky(5 * width, width, 1) for view in VIEW_DOPPLER_COLUMNS})
        self.latent_fuse = nn.ModuleDict({view: ConvBnLeaky(3 * width, width, 1) for view in ("rd", "ra")})
        self.decoders = nn.ModuleDict({
            view: ViewDecoder(width=width, num_classes=num_classes, doppler_columns=VIEW_DOPPLER_COLUMNS[view])
            for view in ("rd", "ra")})
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """The reference's initialisation: Xavier-uniform 2-D conv weights, zero biases (transposed and
        3-D convs, norms keep PyTorch's defaults)."""
        for module in self.modules():
            if type(module) is nn.Conv2d:
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    def _check(self, rd: torch.Tensor, ra: torch.Tensor, ad: torch.Tensor) -> None:
        shapes = {"rd": tuple(rd.shape), "ra": tuple(ra.shape), "ad": tuple(ad.shape)}
        if any(len(s) != 4 or s[1] != self.n_frames for s in shapes.values()):
            raise ValueError(f"expected views (B, {self.n_frames}, H, W), got {shapes}")
        (b, _, r, d), (_, _, r_ra, a), (_, _, a_ad, d_ad) = shapes["rd"], shapes["ra"], shapes["ad"]
        if r_ra != r or a_ad != a or d_ad != d or ra.shape[0] != b or ad.shape[0] != b:
            raise ValueError(f"views disagree: RD (R, D), RA (R, A) and AD (A, D) must share R, A, D; got {shapes}")
        if r % 4 or a % 4:
            raise ValueError(f"range and angle bins must be multiples of 4, got R={r}, A={a}")

    def forward(self, rd: torch.Tensor, ra: torch.Tensor, ad: torch.Tensor) -> dict[str, torch.Tensor]:
        self._check(rd, ra, ad)
        encoded = {view: self.encoders[view](frames) for view, frames in (("rd", rd), ("ra", ra), ("ad", ad))}
        summary = {view: self.aspp_fuse[view](self.aspp[view](features))  # (B, W, H/4, W')
                   for view, (features, _) in encoded.items()}
        outputs = {}
        for view in ("rd", "ra"):
            grid = tuple(summary[view].shape[-2:])
            latents = torch.cat([_to_grid(encoded[v][1], grid) for v in ("rd", "ra", "ad")], dim=1)  # (B, 3W, ...)
            fused = self.latent_fuse[view](latents)
            features = torch.cat([summary[view], fused, _to_grid(summary["ad"], grid)], dim=1)  # (B, 3W, ...)
            outputs[view] = self.decoders[view](features)
        return outputs
