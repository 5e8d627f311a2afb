"""Lovasz-softmax (Berman, Triki and Blaschko, CVPR 2018): a convex surrogate of each class's Jaccard loss.

Cross entropy rewards every voxel alike, so a class of few voxels (pedestrians in an ROI of cars and
background) weighs little in it even when weighted; the Lovasz extension of ``1 - IoU`` is computed per
class, so each present class counts equally, which is what mIoU scores. With hard (one-hot)
probabilities it equals the mean over present classes of ``1 - IoU`` exactly.
"""

from __future__ import annotations

import torch


def lovasz_grad(foreground_sorted: torch.Tensor) -> torch.Tensor:
    """Gradient of the Lovasz extension of the Jaccard loss w.r.t. errors sorted in decreasing order.

    ``foreground_sorted``: (N,) float 0/1, the class's membership in the errors' order.
    """
    total = foreground_sorted.sum()
    intersection = total - foreground_sorted.cumsum(0)
    union = total + (1.0 - foreground_sorted).cumsum(0)
    jaccard = 1.0 - intersection / union
    if len(foreground_sorted) > 1:
        jaccard[1:] = jaccard[1:] - jaccard[:-1].clone()
    return jaccard


def lovasz_softmax(probabilities: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Mean Lovasz-softmax loss over the classes present in ``labels``.

    Args:
        probabilities: (N, C) softmax probabilities of N voxels.
        labels: (N,) int64 class of each voxel.

    Returns:
        A scalar; 0 for an empty batch.
    """
    if probabilities.ndim != 2 or labels.shape != probabilities.shape[:1]:
        raise ValueError(f"expected probabilities (N, C) and labels (N,), got {tuple(probabilities.shape)} and "
                         f"{tuple(labels.shape)}")
    losses = []
    for c in range(probabilities.shape[1]):
        foreground = (labels == c).to(probabilities.dtype)
        if not foreground.any():  # an absent class has no IoU to lose
            continue
        errors = (foreground - probabilities[:, c]).abs()
        errors_sorted, order = torch.sort(errors, descending=True)
        losses.append(torch.dot(errors_sorted, lovasz_grad(foreground[order])))
    return torch.stack(losses).mean() if losses else probabilities.sum() * 0.0
