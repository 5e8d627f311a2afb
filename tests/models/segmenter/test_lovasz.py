"""Lovasz-softmax: the exact Jaccard loss on hard predictions, a usable gradient on soft ones."""

import numpy as np
import pytest
import torch

from models.segmenter.lovasz import lovasz_softmax


def _iou_loss(labels: np.ndarray, prediction: np.ndarray, num_classes: int) -> float:
    """Mean over the classes present in ``labels`` of 1 - IoU (by counting)."""
    losses = []
    for c in range(num_classes):
        truth, predicted = labels == c, prediction == c
        if truth.any():
            losses.append(1.0 - (truth & predicted).sum() / (truth | predicted).sum())
    return float(np.mean(losses))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hard_predictions_give_the_jaccard_loss(seed):
    rng = np.random.default_rng(seed)
    labels = rng.choice(4, size=300, p=[0.7, 0.05, 0.1, 0.15])
    prediction = np.where(rng.random(300) < 0.7, labels, rng.integers(0, 4, 300))
    one_hot = torch.nn.functional.one_hot(torch.from_numpy(prediction), 4).double()
    found = float(lovasz_softmax(one_hot, torch.from_numpy(labels)))
    assert found == pytest.approx(_iou_loss(labels, prediction, 4), abs=1e-9)


def test_a_rare_class_weighs_as_much_as_a_common_one():
    # 1000 background voxels, 10 pedestrian voxels; missing all pedestrians costs (1 - 0) / 2 = 0.5 and
    # not 10 / 1010 as in unweighted accuracy
    labels = torch.cat([torch.zeros(1000, dtype=torch.int64), torch.ones(10, dtype=torch.int64)])
    all_background = torch.nn.functional.one_hot(torch.zeros(1010, dtype=torch.int64), 2).double()
    assert float(lovasz_softmax(all_background, labels)) == pytest.approx((1 - 1000 / 1010 + 1.0) / 2)


def test_gradient_lowers_the_loss_and_bad_shapes_are_named():
    torch.manual_seed(0)
    labels = torch.randint(0, 3, (64,))
    logits = torch.zeros(64, 3, requires_grad=True)
    first = lovasz_softmax(logits.softmax(1), labels)
    first.backward()
    with torch.no_grad():
        stepped = logits - 5.0 * logits.grad
    assert float(lovasz_softmax(stepped.softmax(1), labels)) < float(first.detach())
    assert float(lovasz_softmax(torch.eye(3)[labels], labels)) == 0.0
    with pytest.raises(ValueError, match=r"probabilities \(N, C\) and labels \(N,\)"):
        lovasz_softmax(torch.zeros(4, 3), torch.zeros(5, dtype=torch.int64))
