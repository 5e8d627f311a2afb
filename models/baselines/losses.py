"""The reference (MVRSS) losses of the multi-view baselines (docs/design.md section 9).

Per view: ``0.5 * weighted CE + 5 * soft Dice`` (MVRSS averages ``[CE, 10 * Dice]``); for the
multi-view networks, plus ``5 * coherence`` between the RA and RD range profiles. Class weights are the
inverse class frequencies of the training masks, normalised to sum to 1 (how MVRSS's weight files
are made: their four values sum to 1 and background gets about 1e-4).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

CE_WEIGHT = 0.5
DICE_WEIGHT = 5.0
COHERENCE_WEIGHT = 5.0
DICE_EPS = 1e-6


def class_weights_from_counts(counts: Sequence[int] | np.ndarray) -> torch.Tensor:
    """(C,) float32 weights ``(1 / n_c) / sum_j (1 / n_j)`` from per-class pixel counts ``n`` (C,).

    A class never seen (count 0) gets the largest weight of the seen classes before normalising (it
    cannot matter in training and must not be infinite). Raises ``ValueError`` when nothing was counted.
    """
    counts = np.asarray(counts, np.float64).reshape(-1)
    if counts.size < 2 or (counts < 0).any() or not (counts > 0).any():
        raise ValueError(f"counts must be >= 2 non-negative class counts, not all zero; got {counts.tolist()}")
    seen = counts > 0
    inverse = np.zeros_like(counts)
    inverse[seen] = 1.0 / counts[seen]
    inverse[~seen] = inverse[seen].max()
    return torch.tensor(inverse / inverse.sum(), dtype=torch.float32)


def soft_dice_loss(logits: torch.Tensor, target: torch.Tensor, *, eps: float = DICE_EPS) -> torch.Tensor:
    """Soft Dice loss with squared cardinalities (MVRSS's form), averaged over the batch.

    Args:
        logits: (B, C, H, W) scores; softmax over C gives ``p``.
        target: (B, H, W) int64 class ids in ``[0, C)``; ``t`` is its one-hot.

    Returns:
        scalar ``mean_b (1 - 2 sum(p t) / (sum(p^2) + sum(t^2) + eps))``, sums over classes and pixels.
    """
    if logits.ndim != 4 or target.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(f"expected logits (B, C, H, W) and target (B, H, W), got {tuple(logits.shape)} and "
                         f"{tuple(target.shape)}")
    prob = logits.softmax(dim=1)
    one_hot = F.one_hot(target.long(), logits.shape[1]).permute(0, 3, 1, 2).to(prob.dtype)  # (B, C, H, W)
    intersection = (prob * one_hot).sum(dim=(1, 2, 3))
    cardinality = (prob.square() + one_hot).sum(dim=(1, 2, 3))  # one-hot squared is itself
    return (1.0 - 2.0 * intersection / (cardinality + eps)).mean()


def range_profile(logits: torch.Tensor) -> torch.Tensor:
    """(B, C, R) per range bin and class, the largest class probability along the columns of a view's
    logits (B, C, R, W): what the coherence loss compares between RA and RD."""
    return logits.softmax(dim=1).amax(dim=3)


def coherence_loss(rd_logits: torch.Tensor, ra_logits: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of the RD and RA range profiles (:func:`range_profile`), unweighted.

    ``rd_logits`` (B, C, R, D), ``ra_logits`` (B, C, R, A), both with range bin 0 nearest (our frame; the
    reference flips RD along range because CARRADA stores RA far-first). Zero exactly when, for every
    range bin and class, the most confident angle cell and the most confident Doppler cell agree.
    """
    if rd_logits.shape[:3] != ra_logits.shape[:3]:
        raise ValueError(f"RD {tuple(rd_logits.shape)} and RA {tuple(ra_logits.shape)} must share (B, C, R)")
    return F.mse_loss(range_profile(rd_logits), range_profile(ra_logits))


class MultiViewLoss(nn.Module):
    """The MVRSS training loss over whichever views a model predicts.

    ``forward(outputs, masks)``: ``outputs`` maps view names (``"rd"``, ``"ra"``) to logits
    (B, C, H, W); ``masks`` the same names to (B, H, W) int64 class ids. Returns a dict of named
    scalars: ``{view}_ce`` (weighted CE), ``{view}_dice``, ``coherence`` (when both views are
    predicted) and ``total = sum_v (ce_w * ce_v + dice_w * dice_v) + coherence_w * coherence``.
    """

    def __init__(self, class_weights: Mapping[str, torch.Tensor], *, ce_weight: float = CE_WEIGHT,
                 dice_weight: float = DICE_WEIGHT, coherence_weight: float = COHERENCE_WEIGHT) -> None:
        super().__init__()
        if not class_weights:
            raise ValueError("give class weights for at least one view")
        for view, weights in class_weights.items():
            self.register_buffer(f"weights_{view}", torch.as_tensor(weights, dtype=torch.float32).clone())
        self.views = tuple(class_weights)
        self.ce_weight = ce_weight
        self.dice_weight = dice_weight
        self.coherence_weight = coherence_weight

    def forward(self, outputs: Mapping[str, torch.Tensor],
                masks: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        missing = [view for view in outputs if view not in self.views or view not in masks]
        if missing:
            raise ValueError(f"views {missing} have no class weights or no masks (weights for {self.views}, "
                             f"masks for {sorted(masks)})")
        losses: dict[str, torch.Tensor] = {}
        total = 0.0
        for view, logits in outputs.items():
            target = masks[view].long()
            losses[f"{view}_ce"] = F.cross_entropy(logits, target, weight=getattr(self, f"weights_{view}"))
            losses[f"{view}_dice"] = soft_dice_loss(logits, target)
            total = total + self.ce_weight * losses[f"{view}_ce"] + self.dice_weight * losses[f"{view}_dice"]
        if "rd" in outputs and "ra" in outputs:
            losses["coherence"] = coherence_loss(outputs["rd"], outputs["ra"])
            total = total + self.coherence_weight * losses["coherence"]
        losses["total"] = total
        return losses
