"""The detector stage: the centre detector on normalised log power ``(B, D, R, A)``; targets built from
the store's object table (:func:`models.detector.targets.build_centre_targets`); docs/design.md section 5 losses
(focal + L1 offset + L1 Doppler); random left-right flips from the Dataset (angle bin ``a -> (A - a) mod A``,
offsets and heatmap recomputed, range never flipped). Validation: loss and detection AP at 1/3/5 m."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from models.capabilities import Stage
from pipelines.datasets.store import OBJECT_COLUMN, StoreDataset
from pipelines.evaluation.scoring import centre_targets, score_detector
from pipelines.training.task import Task, unwrap
from radar.errors import UserError


class DetectorTask(Task):
    stage = Stage.DETECTOR
    monitor = "val_mAP"

    def train_dataset(self) -> Dataset:
        """Training frames with their log power in dB (normalised in :meth:`collate`)."""
        return StoreDataset(self.store.path, self.cfg.train_split, fields=("input", "objects"), normalise=False,
                            flip_prob=self.hyper.flip_prob, seed=self.cfg.seed, history=self._history_frames(),
                            history_drop=self.hyper.history_drop)

    def _history_frames(self) -> int:
        return int(self.hyper.model_config.get("history_frames", 0))

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        """Input ``(B, D, R, A)`` normalised with the store's global mean and std (dB), exactly what
        :class:`models.erasenet.model.EraseNet` does at inference, and the centre targets."""
        grid = (self.store.profile.n_range, self.store.profile.n_angle)
        log_power = torch.stack([s["input"] for s in samples])
        stats = self.store.normalisation
        history = {}
        if self._history_frames():
            history = {"history": (torch.stack([s["history"] for s in samples]) - stats["mean"]) / stats["std"],
                       "history_present": torch.stack([s["history_present"] for s in samples])}
            history["history"] *= history["history_present"][:, :, None, None, None]  # absent frames stay 0
        return {"input": (log_power - stats["mean"]) / stats["std"], **history,
                "targets": centre_targets(samples, grid, centre_weights=self._centre_weights(samples),
                                          heatmap_classes=int(self.hyper.model_config.get("heatmap_classes", 1)))}

    def _centre_weights(self, samples: list[dict[str, Any]]) -> list[np.ndarray] | None:
        """Each object's weight in the centre loss: its class's ``class_weights`` entry (None: all 1)."""
        weights = self.hyper.class_weights
        if not weights:
            return None
        n_classes = len(self.store.class_names) - 1
        if len(weights) != n_classes:
            raise UserError(f"--class-weights: {len(weights)} weights for {n_classes} classes "
                            f"{list(self.store.class_names[1:])}")
        table = np.asarray([1.0, *weights], np.float32)  # class id 0 (background) never has a centre
        return [table[np.asarray(s["objects"][:int(s["n_objects"]), OBJECT_COLUMN["class_id"]], np.int64)]
                for s in samples]

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        history = {k: batch[k].to(device) for k in ("history", "history_present") if k in batch}
        outputs = model(batch["input"].to(device), **history)
        targets = {k: v.to(device) for k, v in batch["targets"].items()}
        return unwrap(model).compute_loss(outputs, targets)

    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        if not self.cfg.val_split:
            return {}
        scores = score_detector(model, self.store.path, self.cfg.val_split, self.store.profile,
                                self.store.normalisation, max_frames=self.hyper.val_frames, device=device,
                                with_loss=True, history=self._history_frames())
        if self._history_frames():  # a model that reads history is scored on single cubes too
            single = score_detector(model, self.store.path, self.cfg.val_split, self.store.profile,
                                    self.store.normalisation, max_frames=self.hyper.val_frames, device=device)
            scores.update({f"{k}_single": v for k, v in single.items()})
        model.train()
        return {f"val_{k}": v for k, v in scores.items()}
