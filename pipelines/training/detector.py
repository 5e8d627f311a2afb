"""The detector stage: the centre detector on normalised log power ``(B, D, R, A)``; targets built from
the store's object table (:func:`models.detector.targets.build_centre_targets`); docs/design.md section 5 losses
(focal + L1 offset + L1 Doppler); random left-right flips from the Dataset (angle bin ``a -> (A - a) mod A``,
offsets and heatmap recomputed, range never flipped). With a crop (``--crop R A``, the ``crops`` recipe) it trains
on range x angle windows of the frames (:mod:`pipelines.training.windows`), their targets cut from the whole
frame's. Validation (loss and detection AP at 1/3/5 m) is always on whole frames."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from models.capabilities import Stage
from models.detector.targets import crop_centre_targets
from pipelines.datasets.spread import subset
from pipelines.datasets.store import OBJECT_COLUMN, StoreDataset
from pipelines.evaluation.scoring import centre_targets, score_detector
from pipelines.training.task import Task, unwrap
from pipelines.training.windows import WindowDataset, WindowSampler, whole_frame_batch_norms
from radar.errors import UserError

BATCH_NORM_FRAMES = 64
"""Whole train frames whose statistics a crop-trained detector's BatchNorms take before each validation."""


class DetectorTask(Task):
    stage = Stage.DETECTOR
    monitor = "val_mAP"

    def train_dataset(self) -> Dataset:
        """Training frames with their log power in dB (normalised in :meth:`collate`)."""
        sampler = self.window_sampler()
        frames = StoreDataset(self.store.path, self.cfg.train_split, fields=("input", "objects"), normalise=False,
                              flip_prob=self.hyper.flip_prob, seed=self.cfg.seed, history=self._history_frames(),
                              history_drop=self.hyper.history_drop,
                              doppler_last=sampler is not None and not self._history_frames())
        return frames if sampler is None else WindowDataset(frames, sampler, seed=self.cfg.seed)

    def build_model(self) -> nn.Module:
        """The detector; in NHWC memory format where the recipe says so (the same weights and arithmetic, only
        the layout of the activations changes: benchmarks.detector_crops measures the step)."""
        model = super().build_model()
        return model.to(memory_format=torch.channels_last) if self.hyper.channels_last else model

    def window_sampler(self) -> WindowSampler | None:
        """The windows trained on (None: whole frames)."""
        if not self.hyper.crop:
            return None
        grid = (self.store.profile.n_range, self.store.profile.n_angle)
        try:
            return WindowSampler(tuple(self.hyper.crop), grid, object_share=self.hyper.crop_object_share)
        except ValueError as exc:
            raise UserError(f"--crop {self.hyper.crop[0]} {self.hyper.crop[1]} on the {grid[0]} x {grid[1]} grid "
                            f"of {self.store.profile.name!r}: {exc}") from None

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
        targets = centre_targets(samples, grid, centre_weights=self._centre_weights(samples),
                                 heatmap_classes=int(self.hyper.model_config.get("heatmap_classes", 1)))
        windows = {}
        if "window_origin" in samples[0]:  # crop training: the whole frames' targets cut to the windows
            origins = torch.stack([s["window_origin"] for s in samples])  # (B, 2) bins
            sampler = self.window_sampler()
            targets = crop_centre_targets(targets, (origins // sampler.stride).tolist(), sampler.cells)
            windows = {"window_origins": origins}
        log_power = (log_power - stats["mean"]) / stats["std"]
        if self.hyper.channels_last:
            log_power = log_power.contiguous(memory_format=torch.channels_last)
        return {"input": log_power, **history, **windows, "targets": targets}

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

    def _whole_frames(self, device: torch.device) -> Iterator[dict[str, torch.Tensor]]:
        """Batches of whole train frames, evenly spread, normalised as in training (no flips, no history): what
        a crop-trained detector's BatchNorm statistics are taken from."""
        frames = StoreDataset(self.store.path, self.cfg.train_split, fields=("input",), normalise=False)
        indices = subset(len(frames), BATCH_NORM_FRAMES)
        stats = self.store.normalisation
        for start in range(0, len(indices), self.hyper.batch_size):
            log_power = torch.stack([frames[i]["input"] for i in indices[start:start + self.hyper.batch_size]])
            log_power = ((log_power - stats["mean"]) / stats["std"]).to(device)
            if self.hyper.channels_last:
                log_power = log_power.contiguous(memory_format=torch.channels_last)
            yield {"log_power": log_power}

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        history = {k: batch[k].to(device) for k in ("history", "history_present", "window_origins") if k in batch}
        outputs = model(batch["input"].to(device), **history)
        targets = {k: v.to(device) for k, v in batch["targets"].items()}
        return unwrap(model).compute_loss(outputs, targets)

    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        if self.hyper.crop:  # the checkpoint taken after validation carries these statistics too
            whole_frame_batch_norms(unwrap(model), self._whole_frames(device))
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
