"""The segmenter stage: MinkUNet or SPVCNN on ROI points. Each sample's ROI is grown
(:func:`radar.region_growing.grow_regions`) from the ground-truth centres moved by errors like the
detector's (:mod:`pipelines.training.jitter`: ``--jitter-from DETECTOR_CKPT`` measures them on the
validation split, ``--jitter-std R A D`` gives Gaussian errors instead, stated in the run's ``jitter.json``).
Loss: class-weighted cross entropy (``1 / sqrt(frequency)`` of the classes among ROI voxels of up to 64
training frames, normalised to mean 1; ``class_weights.json``), plus ``--lovasz-weight`` x Lovasz-softmax
(:mod:`models.segmenter.lovasz`) when given. Validation: voxel mIoU over the ROI (picks ``model.pt``), and RA/RD
mIoU and IoU per class of whole frames, as ``radarseg evaluate`` scores them."""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import Dataset

from models.capabilities import Stage
from models.segmenter.lovasz import lovasz_softmax
from pipelines.datasets.spread import subset
from pipelines.datasets.store import StoreDataset, open_store
from pipelines.datasets.store_info import StoreInfo
from pipelines.evaluation.scoring import ViewConfusion, frame_centres
from pipelines.jobs import smoke_mode
from pipelines.training.jitter import SeedJitter, measure_detector_errors
from pipelines.training.task import Task, unwrap
from radar.metrics import iou_per_class
from radar.region_growing import grow_regions
from radar.roi import roi_points
from radar.transforms import project_voxels

log = logging.getLogger(__name__)

JITTER_FRAMES = 96  # validation frames on which --jitter-from measures the detector's errors
WEIGHT_FRAMES = 64  # training frames whose ROI voxels give the class weights


def sparse_input(model: nn.Module, batch: dict[str, Any], device: torch.device) -> Any:
    """The segmenter's input for a collated ROI batch, made by the model (``make_input``: a SparseTensor,
    or a PointTensor for SPVCNN)."""
    coords = batch["coords"].to(device)  # (N, 4) int64: batch, range, angle, Doppler bins
    feats = batch["features"].to(device)  # (N, 4)
    return unwrap(model).make_input(coords, feats)


class RoiDataset(Dataset):
    """ROI points of store frames grown from jittered ground-truth centres (segmenter training samples).

    Item: ``coords`` (N, 3) int64 bins, ``features`` (N, 4) float32 (:func:`radar.roi.roi_points`),
    ``labels`` (N,) int64 class per ROI voxel, ``recall`` float, ``frame`` int. Only frames with at
    least one object are used (a frame without seeds has no ROI). The jitter and flips depend on
    ``(seed, epoch, frame)``: call :meth:`set_epoch` before each epoch.
    """

    def __init__(self, store: StoreInfo, split: str, jitter: SeedJitter | None, *, flip_prob: float = 0.0,
                 seed: int = 0, limit: int = 0):
        self.store = store
        self.frames = StoreDataset(store.path, split, fields=("input", "labels", "instances", "objects"),
                                   normalise=False, flip_prob=flip_prob, seed=seed, doppler_last=True)
        n_objects = open_store(store.path)["n_objects"][:]
        keep = [i for i, slot in enumerate(self.frames.frames) if n_objects[slot] > 0]
        self.indices = [keep[i] for i in subset(len(keep), limit)]
        self.jitter = jitter
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, item: int) -> dict[str, Any]:
        sample = self.frames[self.indices[item]]
        log_power = sample["input"].numpy()  # (R, A, D) dB
        seeds = frame_centres(sample)
        if self.jitter is not None:
            rng = np.random.default_rng([self.seed, self.epoch, sample["frame"], 1])
            seeds = seeds + self.jitter.sample(len(seeds), rng)
        profile = self.store.profile
        seeds = np.clip(seeds, 0, np.asarray(profile.shape) - 1)
        regions = grow_regions(log_power, seeds, profile)
        voxels = regions.voxels if len(regions) else regions.seeds  # a seed in the noise grows nothing
        points = roi_points(voxels, log_power, profile, mean_db=self.store.normalisation["mean"],
                            std_db=self.store.normalisation["std"])
        labels = sample["labels"].numpy()[tuple(voxels.T)]
        return {"coords": torch.from_numpy(points.coords), "features": torch.from_numpy(points.features),
                "labels": torch.from_numpy(labels.astype(np.int64)),
                "recall": regions.recall(sample["instances"].numpy()), "frame": sample["frame"]}


def collate_roi(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Concatenate ROI samples into one batch: ``coords`` (N, 4) with the sample index first."""
    coords = [torch.cat([torch.full((len(s["coords"]), 1), b, dtype=torch.int64), s["coords"]], dim=1)
              for b, s in enumerate(samples)]
    return {"coords": torch.cat(coords), "features": torch.cat([s["features"] for s in samples]),
            "labels": torch.cat([s["labels"] for s in samples]),
            "recall": [s["recall"] for s in samples], "frames": [s["frame"] for s in samples]}


class SegmenterTask(Task):
    stage = Stage.SEGMENTER
    monitor = "val_mIoU"
    jitter: SeedJitter
    class_weights: torch.Tensor

    def prepare(self, model: nn.Module, rank: int) -> None:
        jitter_path = self.run_dir / "jitter.json"
        weights_path = self.run_dir / "class_weights.json"
        if jitter_path.is_file():  # resumed run, or written by rank 0 of this run
            self.jitter = SeedJitter.from_dict(json.loads(jitter_path.read_text()))
        elif self.cfg.jitter_from:
            self.jitter = measure_detector_errors(self.cfg.jitter_from, self.store.path,
                                                  self.cfg.val_split or self.cfg.train_split, max_frames=JITTER_FRAMES)
        elif self.cfg.jitter_std is not None:  # asked for: said once, at INFO
            log.info("seeds jittered by Gaussian errors of std %s bins (--jitter-std)", self.hyper.jitter_std)
            self.jitter = SeedJitter(np.zeros((0, 3)), self.hyper.jitter_std, "gaussian (--jitter-std)")
        elif smoke_mode():  # a --jitter-from was cleared by its smoke rule, which warned: not a second warning
            log.info("smoke mode: seeds jittered by Gaussian errors of the default std %s bins", self.hyper.jitter_std)
            self.jitter = SeedJitter(np.zeros((0, 3)), self.hyper.jitter_std, "gaussian (smoke mode)")
        else:
            log.warning("neither --jitter-from nor --jitter-std given: seeds jittered by Gaussian errors of the "
                        "default std %s bins", self.hyper.jitter_std)
            self.jitter = SeedJitter(np.zeros((0, 3)), self.hyper.jitter_std, "gaussian (assumed)")
        if weights_path.is_file():
            self.class_weights = torch.tensor(json.loads(weights_path.read_text())["weights"])
        else:
            self.class_weights = self._measure_class_weights()
        if rank == 0:
            jitter_path.write_text(json.dumps(self.jitter.to_dict()))
            weights_path.write_text(json.dumps({"weights": self.class_weights.tolist(),
                                                "classes": list(self.store.class_names)}))

    def _measure_class_weights(self) -> torch.Tensor:
        """``1 / sqrt(frequency)`` of each class among ROI voxels of up to :data:`WEIGHT_FRAMES` training
        frames, normalised to mean 1 over the classes seen (unseen classes get the largest weight)."""
        dataset = RoiDataset(self.store, self.cfg.train_split, self.jitter, seed=self.cfg.seed, limit=WEIGHT_FRAMES)
        counts = np.zeros(self.store.profile.num_classes)
        for i in range(len(dataset)):
            counts += np.bincount(dataset[i]["labels"].numpy(), minlength=len(counts))
        seen = counts > 0
        weights = np.ones_like(counts)
        if seen.any():
            weights[seen] = 1.0 / np.sqrt(counts[seen] / counts.sum())
            weights[seen] /= weights[seen].mean()
            weights[~seen] = weights[seen].max()
        return torch.tensor(weights, dtype=torch.float32)

    def train_dataset(self) -> Dataset:
        return RoiDataset(self.store, self.cfg.train_split, self.jitter, flip_prob=self.hyper.flip_prob,
                          seed=self.cfg.seed)

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        return collate_roi(samples)

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        logits = model(sparse_input(model, batch, device))
        labels = batch["labels"].to(device)
        ce = nn.functional.cross_entropy(logits, labels, weight=self.class_weights.to(device))
        if not self.hyper.lovasz_weight:
            return {"ce": ce, "total": ce}
        lovasz = lovasz_softmax(logits.softmax(1), labels)
        return {"ce": ce, "lovasz": lovasz, "total": ce + self.hyper.lovasz_weight * lovasz}

    @torch.no_grad()
    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        if not self.cfg.val_split:
            return {}
        dataset = RoiDataset(self.store, self.cfg.val_split, self.jitter, seed=self.cfg.seed + 1,
                             limit=self.hyper.val_frames)
        if len(dataset) == 0:
            return {}
        model.eval()
        profile = self.store.profile
        confusion = ViewConfusion(profile.num_classes, views=("roi", "ra", "rd"))
        root = open_store(self.store.path)
        truth_views = {"ra": root["ra_mask"], "rd": root["rd_mask"]}
        recalls = []
        for start in range(0, len(dataset), 4):
            batch = collate_roi([dataset[i] for i in range(start, min(start + 4, len(dataset)))])
            prediction = model(sparse_input(model, batch, device)).argmax(1).cpu().numpy()
            confusion.add("roi", batch["labels"].numpy(), prediction)
            recalls += batch["recall"]
            coords = batch["coords"].numpy()
            for b, slot in enumerate(batch["frames"]):  # the frame's RA/RD masks, as the evaluator scores them
                mine = coords[:, 0] == b
                for view, axis in (("ra", 2), ("rd", 1)):
                    mask = project_voxels(coords[mine, 1:], prediction[mine], profile.shape, axis, profile.num_classes)
                    confusion.add(view, truth_views[view][slot], mask)
        model.train()
        # mIoU over the ROI voxels (background included), seeds jittered like in training; and the RA/RD views'
        # mIoU and IoU per class over whole frames (background outside the ROI), as `radarseg evaluate` scores them
        figures = {"val_mIoU": confusion.miou("roi"), "val_roi_recall": float(np.mean(recalls))}
        for view in ("ra", "rd"):
            figures[f"val_{view.upper()}_mIoU"] = confusion.miou(view)
            iou = iou_per_class(confusion.matrices[view])
            figures.update({f"val_{view.upper()}_iou_{name}": float(value)
                            for name, value in zip(self.store.class_names, iou, strict=True)})
        return figures

    def extra(self) -> dict[str, Any]:
        return {"jitter": {k: v for k, v in self.jitter.to_dict().items() if k != "residuals"},
                "class_weights": self.class_weights.tolist()}
