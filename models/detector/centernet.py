"""CenterNet heads of the centre detector: forward, loss and decoding (docs/design.md section 5).

Three branches on the stride-``S`` feature map ``(B, C, H, W)``, each a 3x3 conv (dense or depthwise
separable) with ``head_channels`` channels, ReLU, then a 1x1 conv:

- ``heatmap``: 1 channel, or one per foreground class (``heatmap_classes``, CenterNet's own form), sigmoid,
  bias initialised to -2.19 (prior probability 0.1). With classes, the class-agnostic ``heatmap`` that
  decoding, region growing and the exports read is ``max_c min(1, gain_c p_c)``: a class's gain (the buffer
  ``class_gain``, 1 until tuned, carried in the state dict) is its own threshold's correction, so that a weak
  class's peaks meet the one operating threshold (gain 2 for a class: its peaks of 0.15 count as 0.3);
- ``offset``: 2 channels, sub-cell (range, angle) offset of the centre, in cells;
- ``doppler``: 1 channel, the object's mean Doppler bin (bias initialised to ``D / 2``, zero velocity).

Loss (targets as in :mod:`models.detector.targets`): CenterNet's focal loss (alpha 2, beta 4) on the
heatmap, normalised by the number of objects, plus L1 on offset and Doppler read at the object centre
cells, each averaged over objects (and offset components), weights 1 and 1.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from models.detector.targets import CentreTargets
from models.layers import SeparableConv2d, require_at_least

HEATMAP_PRIOR_BIAS = -2.19  # sigmoid(-2.19) = 0.1


def _branch(in_channels: int, head_channels: int, out_channels: int, *, separable: bool) -> nn.Sequential:
    if separable:
        hidden: nn.Module = SeparableConv2d(in_channels, head_channels, 3, norm=False, act="relu")
    else:
        hidden = nn.Sequential(nn.Conv2d(in_channels, head_channels, 3, padding=1), nn.ReLU(inplace=True))
    return nn.Sequential(hidden, nn.Conv2d(head_channels, out_channels, 1))


def focal_loss(heatmap_logits: torch.Tensor, target: torch.Tensor, *, alpha: float = 2.0, beta: float = 4.0,
               peak_weight: torch.Tensor | None = None):
    """CenterNet's penalty-reduced pixel-wise focal loss, summed and divided by the positives.

    ``heatmap_logits`` and ``target`` are ``(B, 1, H, W)``; cells where ``target == 1`` are positives.
    ``loss = -(sum_pos w (1-p)^alpha log p + sum_neg (1-y)^beta p^alpha log(1-p)) / max(n_pos, 1)``,
    with ``p = sigmoid(logits)`` evaluated through ``logsigmoid`` for stability; ``w`` is ``peak_weight`` at the
    positives (``(B, 1, H, W)``, e.g. a class's weight at its objects' centres; 1 without it).
    """
    prob = torch.sigmoid(heatmap_logits)
    log_p = F.logsigmoid(heatmap_logits)
    log_not_p = F.logsigmoid(-heatmap_logits)
    positive = target.eq(1).to(heatmap_logits.dtype)
    negative = 1.0 - positive
    pos_loss = (1 - prob).pow(alpha) * log_p * (positive if peak_weight is None else positive * peak_weight)
    neg_loss = (1 - target).pow(beta) * prob.pow(alpha) * log_not_p * negative
    num_pos = positive.sum().clamp(min=1.0)
    return -(pos_loss.sum() + neg_loss.sum()) / num_pos


def _gather(feature: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    """Values of ``feature`` ``(B, C, H, W)`` at flat cell ``indices`` ``(B, K)`` -> ``(B, K, C)``."""
    batch, channels = feature.shape[:2]
    flat = feature.reshape(batch, channels, -1)
    return flat.gather(2, indices.unsqueeze(1).expand(batch, channels, indices.shape[1])).transpose(1, 2)


class CentreNetHead(nn.Module):
    """Heatmap, offset and Doppler heads; ``forward`` returns a dict of named outputs.

    Outputs for features ``(B, in_channels, H, W)``: ``heatmap`` (B, 1, H, W) probabilities (class-agnostic),
    ``heatmap_logits`` (B, C, H, W), with ``C`` heatmap classes also ``class_heatmap`` (B, C, H, W),
    ``offset`` (B, 2, H, W) cells (range, angle), ``doppler``
    (B, 1, H, W) Doppler bins.
    """

    def __init__(
        self,
        *,
        doppler_bins: int,
        in_channels: int = 64,
        head_channels: int = 64,
        separable: bool = False,
        output_stride: int = 4,
        offset_weight: float = 1.0,
        doppler_weight: float = 1.0,
        focal_alpha: float = 2.0,
        focal_beta: float = 4.0,
        heatmap_classes: int = 1,
    ) -> None:
        super().__init__()
        require_at_least(1, doppler_bins=doppler_bins, in_channels=in_channels, head_channels=head_channels,
                         output_stride=output_stride, heatmap_classes=heatmap_classes)
        self.heatmap = _branch(in_channels, head_channels, heatmap_classes, separable=separable)
        self.heatmap_classes = heatmap_classes
        if heatmap_classes > 1:
            self.register_buffer("class_gain", torch.ones(heatmap_classes))
        self.offset = _branch(in_channels, head_channels, 2, separable=separable)
        self.doppler = _branch(in_channels, head_channels, 1, separable=separable)
        nn.init.constant_(self.heatmap[-1].bias, HEATMAP_PRIOR_BIAS)
        nn.init.constant_(self.doppler[-1].bias, doppler_bins / 2)
        self.doppler_bins = doppler_bins
        self.output_stride = output_stride
        self.offset_weight = offset_weight
        self.doppler_weight = doppler_weight
        self.focal_alpha = focal_alpha
        self.focal_beta = focal_beta

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        logits = self.heatmap(features)
        per_class = {}
        heatmap = torch.sigmoid(logits)
        if self.heatmap_classes > 1:
            per_class = {"class_heatmap": heatmap}
            heatmap = (heatmap * self.class_gain[:, None, None]).clamp(max=1.0).amax(dim=1, keepdim=True)
        return {
            **per_class,
            "heatmap": heatmap,
            "heatmap_logits": logits,
            "offset": self.offset(features),
            "doppler": self.doppler(features),
        }

    def compute_loss(
        self, outputs: dict[str, torch.Tensor], targets: CentreTargets
    ) -> dict[str, torch.Tensor]:
        """Named losses ``heatmap``, ``offset``, ``doppler`` and their weighted sum ``total`` (scalars).

        ``targets`` as described in :mod:`models.detector.targets`, on the same grid as ``outputs``.
        """
        logits = outputs["heatmap_logits"]
        if targets["heatmap"].shape != logits.shape:
            raise ValueError(
                f"target heatmap shape {tuple(targets['heatmap'].shape)} does not match the output "
                f"{tuple(logits.shape)}"
            )
        heatmap_loss = focal_loss(logits, targets["heatmap"], alpha=self.focal_alpha, beta=self.focal_beta,
                                  peak_weight=targets.get("peak_weight"))
        mask = targets["mask"].to(logits.dtype)  # (B, K)
        num_objects = mask.sum()
        indices = targets["indices"]
        offset_pred = _gather(outputs["offset"], indices)  # (B, K, 2)
        doppler_pred = _gather(outputs["doppler"], indices)[..., 0]  # (B, K)
        offset_loss = ((offset_pred - targets["offsets"]).abs() * mask[..., None]).sum() / (
            2 * num_objects + 1e-4
        )
        doppler_loss = ((doppler_pred - targets["doppler"]).abs() * mask).sum() / (num_objects + 1e-4)
        total = heatmap_loss + self.offset_weight * offset_loss + self.doppler_weight * doppler_loss
        return {"heatmap": heatmap_loss, "offset": offset_loss, "doppler": doppler_loss, "total": total}

    @torch.no_grad()
    def decode(
        self, outputs: dict[str, torch.Tensor], k: int = 100, score_threshold: float = 0.1
    ) -> list[dict[str, torch.Tensor]]:
        """Centres per frame: 3x3 max-pool peaks, top-``k``, ``score >= score_threshold``.

        Returns one dict per frame with 1-D tensors of equal length ``n <= k``, sorted by descending
        score: ``score`` (0..1), ``range_bin`` and ``angle_bin`` (fractional input bins, ``(cell +
        offset) * S``), ``doppler_bin`` (fractional Doppler bin).
        """
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        heatmap = outputs["heatmap"]  # (B, 1, H, W)
        batch, _, height, width = heatmap.shape
        peaks = F.max_pool2d(heatmap, kernel_size=3, stride=1, padding=1).eq(heatmap)
        scores = (heatmap * peaks).reshape(batch, -1)
        top_scores, top_indices = scores.topk(min(k, height * width), dim=1)  # (B, k)
        offsets = _gather(outputs["offset"], top_indices)  # (B, k, 2)
        doppler = _gather(outputs["doppler"], top_indices)[..., 0]  # (B, k)
        rows = torch.div(top_indices, width, rounding_mode="floor").to(heatmap.dtype)
        cols = (top_indices % width).to(heatmap.dtype)
        range_bin = (rows + offsets[..., 0]) * self.output_stride
        angle_bin = (cols + offsets[..., 1]) * self.output_stride
        detections = []
        for b in range(batch):
            keep = top_scores[b] >= score_threshold
            detections.append(
                {
                    "score": top_scores[b][keep],
                    "range_bin": range_bin[b][keep],
                    "angle_bin": angle_bin[b][keep],
                    "doppler_bin": doppler[b][keep],
                }
            )
        return detections
