"""The 2-D baselines' stage (U-Net per view, TMVA-Net, SMVA-Net; docs/design.md section 9).

Data: :class:`pipelines.datasets.views.ViewDataset` (RD/RA/AD views scaled by the train split's min/max; TMVA-Net
reads the target frame and the 4 before it in its sequence, so the first 4 frames of each sequence
are not used, as in the reference). Loss: :class:`models.baselines.losses.MultiViewLoss` (per view
0.5 x weighted CE + 5 x soft Dice, plus 5 x coherence for the two-view networks), class weights the
normalised inverse pixel frequencies of the train split's RD and RA masks. Optimiser as in the reference:
Adam, learning rate multiplied by ``gamma`` every ``step_every`` epochs; random left-right (angle)
mirroring of whole windows. The checkpoint's ``normalisation`` is the view scaling; the class weights,
frame count and views are in its ``extra``. Validation: mIoU, mean over the predicted views.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn
from torch.utils.data import Dataset

from models.baselines.losses import MultiViewLoss, class_weights_from_counts
from models.capabilities import Stage
from pipelines.datasets.views import (
    ViewDataset,
    ViewStats,
    collate_views,
    masks_of,
    model_inputs,
    view_class_counts,
)
from pipelines.evaluation.scoring import predicted_views, score_baseline
from pipelines.training.task import Task


class BaselineTask(Task):
    stage = Stage.BASELINE
    monitor = "val_mIoU"
    views: tuple[str, ...]
    stats: ViewStats
    weights: dict[str, torch.Tensor]
    loss_fn: MultiViewLoss
    n_frames: int
    dataset: ViewDataset

    def prepare(self, model: nn.Module, rank: int) -> None:
        self.views = predicted_views(model)
        self.n_frames = model.n_frames
        self.stats = ViewStats.from_store(self.cfg.store, self.cfg.train_split)
        counts = view_class_counts(self.cfg.store, self.cfg.train_split)
        self.weights = {view: class_weights_from_counts(counts[view]) for view in self.views}
        self.loss_fn = MultiViewLoss(self.weights).to(next(model.parameters()).device)
        self.dataset = ViewDataset(self.cfg.store, self.cfg.train_split, n_frames=self.n_frames, stats=self.stats,
                                   flip_prob=self.hyper.flip_prob, seed=self.cfg.seed)

    def train_dataset(self) -> Dataset:
        return self.dataset

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        return collate_views(samples)

    def batch_size_of(self, batch: dict[str, Any]) -> int:
        return len(batch["frame"])

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        return self.loss_fn(model(*model_inputs(model, batch, device)), masks_of(batch, device))

    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        if not self.cfg.val_split:
            return {}
        val_set = ViewDataset(self.cfg.store, self.cfg.val_split, n_frames=self.n_frames, stats=self.stats,
                              limit=self.hyper.val_frames)
        if not len(val_set):
            return {}
        scores = score_baseline(model, val_set, num_classes=self.store.profile.num_classes, loss_fn=self.loss_fn,
                                device=device)
        model.train()
        return {f"val_{k}": v for k, v in scores.items() if not k.startswith(("confusion", "iou"))}

    def normalisation(self) -> dict[str, Any]:
        return self.stats.to_dict()

    def extra(self) -> dict[str, Any]:
        return {"n_frames": self.n_frames, "views": list(self.views),
                "class_weights": {view: w.tolist() for view, w in self.weights.items()},
                "train_frames": len(self.dataset)}
