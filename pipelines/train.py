"""Training of both ERASE-Net stages from the preprocessed store (issue 6; SPEC sections 5 and 7).

The job is ``parse_args() -> main(cfg) -> dict``::

    python -m pipelines.train detector  --store STORE.zarr --out runs/det [--profile quick|paper] [--resume]
    python -m pipelines.train segmenter --store STORE.zarr --out runs/seg --jitter-from runs/det/model.pt
    radarseg train detector|segmenter ...                       # the same arguments
    radarseg train export RUN/model.pt checkpoints/detector.pt  # shippable copy: float16 weights only

Stages (a :class:`StageTask` each, picked once from :data:`TASKS`):

- ``detector``: the centre detector on normalised log power ``(B, D, R, A)``; targets built from the
  store's object table (:func:`models.detector.targets.build_centre_targets`); SPEC section 5 losses
  (focal + L1 offset + L1 Doppler); Adam with a step schedule; random left-right flips from the
  Dataset (angle bin ``a -> (A - a) mod A``, offsets and heatmap recomputed, range never flipped).
  Validation: loss and detection AP at 1/3/5 m (:mod:`radar.metrics`).
- ``segmenter``: MinkUNet or SPVCNN on ROI points. Each sample's ROI is grown
  (:func:`radar.region_growing.grow_regions`) from the ground-truth centres moved by errors like the
  detector's: ``--jitter-from DETECTOR_CKPT`` measures them on the validation split (matched pairs
  within 3 m; residuals in range/angle/Doppler bins, resampled during training), ``--jitter-std R A D``
  gives Gaussian errors instead (the ``quick`` default, stated in the run's ``jitter.json``). Loss:
  class-weighted cross entropy (weights ``1 / sqrt(frequency)`` of the classes among ROI voxels of up
  to 64 training frames, normalised to mean 1). SGD with momentum and a per-step cosine decay.

Profiles (:data:`PROFILES`, data): ``paper`` is the paper's recipe (detector: Adam 1e-4 divided by 10
every 10 epochs, 300 epochs; segmenter: SGD from 0.24 with cosine decay, 300 epochs); ``quick`` is
what converges on a 2-core CPU on the ``small`` preset in about an hour for both stages. Any
hyperparameter can be overridden (``--epochs``, ``--batch-size``, ``--lr``, ``--model``, ``--model-config``).

Run directory ``--out``: ``config.json`` (the resolved configuration), ``metrics.jsonl`` (one JSON line
per epoch: train losses, lr, seconds, samples/s, validation metrics), ``last.pt`` (model, optimiser
and scheduler state: ``--resume`` continues from it), ``model.pt`` (weights only, the epoch with the
best validation score: what you ship), plus ``jitter.json`` and ``class_weights.json`` for the
segmenter. Checkpoints are :class:`models.checkpoint.Checkpoint`: a model rebuilds from one alone,
with its preset, class names and the store's normalisation statistics (``mean``, ``std`` in dB and
``mean_per_doppler``/``std_per_doppler`` lists, D values).

Network slimming (SPEC section 11, :mod:`models.slimming`): ``--slim-lambda [L]`` adds ``L * sum |gamma|``
over every BatchNorm scale to the loss (``slim_l1`` in the metrics; ``L`` is 1e-4 when the flag is given
alone); ``--init CKPT`` starts from a checkpoint's architecture and weights (a pruned one carries its
narrower ``channels`` table), for fine-tuning after ``radarseg prune``.

``--ray-workers N`` runs the same loop data-parallel under Ray Train's ``TorchTrainer`` (gloo on CPU,
NCCL on GPU), against an embedded local Ray or ``--address``; rank 0 writes the run directory (it
must be on storage every worker sees). Without it nothing of Ray is imported. Epochs are shuffled
from ``(seed, epoch)``, so a resumed run sees the same order as a straight one.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm import tqdm

from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.detector.targets import build_centre_targets
from models.registry import create_model
from models.segmenter.spvcnn import SPVCNN, PointTensor
from models.slimming import slimming_penalty
from models.sparse import SparseTensor
from pipelines.store import OBJECT_FIELDS, StoreDataset, open_store
from radar.metrics import DetectionEvaluator, confusion_matrix, mean_iou
from radar.profiles import RadarProfile, get_profile
from radar.region_growing import grow_regions
from radar.roi import roi_points

log = logging.getLogger(__name__)

STAGES = ("detector", "segmenter")
COL = {name: i for i, name in enumerate(OBJECT_FIELDS)}
CENTRE_COLUMNS = [COL["range_bin"], COL["angle_bin"], COL["doppler_bin"]]
JITTER_MATCH_M = 3.0  # a detection within this many metres (and bins of Doppler) of a truth is "its" detection
RAY_OBJECT_STORE_BYTES = 200_000_000


@dataclass(frozen=True)
class Hyper:
    """Hyperparameters of one stage under one profile (every field may be overridden)."""

    model: str
    model_config: dict[str, Any]
    epochs: int
    batch_size: int
    lr: float
    weight_decay: float = 0.0
    momentum: float = 0.9  # SGD only
    milestones: tuple[float, ...] = ()  # fractions of the epochs where a step schedule multiplies the lr by gamma
    step_every: int = 0  # or every this many epochs (0 = use milestones)
    gamma: float = 0.1
    flip_prob: float = 0.5
    val_frames: int = 0  # frames of the validation split used per epoch (0 = all)
    jitter_std: tuple[float, float, float] = (1.0, 1.0, 0.5)  # segmenter, bins, when no detector is given
    optimizer: str = ""  # "" = the stage's own (detector Adam, segmenter SGD); or "adam" / "sgd"


OPTIMIZERS = ("adam", "sgd")
def make_optimizer(hyper: Hyper, params, *, default: str) -> torch.optim.Optimizer:
    """The stage's optimiser (``default``) unless ``hyper.optimizer`` names another: Adam, or SGD with Nesterov
    momentum. Adam drives unneeded BatchNorm scales to zero under the slimming penalty within a short run; SGD's
    steps of lr x lambda barely move them (reports/slimming.md)."""
    name = hyper.optimizer or default
    if name == "adam":
        return torch.optim.Adam(params, lr=hyper.lr, weight_decay=hyper.weight_decay)
    return torch.optim.SGD(params, lr=hyper.lr, momentum=hyper.momentum, weight_decay=hyper.weight_decay,
                           nesterov=True)


PROFILES: dict[str, dict[str, Hyper]] = {
    "detector": {
        # The paper: Adam, 1e-4, divided by 10 every 10 epochs, 300 epochs (read literally).
        "paper": Hyper("centre_detector", {}, epochs=300, batch_size=16, lr=1e-4, step_every=10),
        "quick": Hyper("centre_detector", {}, epochs=12, batch_size=8, lr=2e-3, weight_decay=0.0,
                       milestones=(0.67, 0.88), val_frames=96),
    },
    "segmenter": {
        "paper": Hyper("minkunet", {"ratio": 0.37}, epochs=300, batch_size=8, lr=0.24, weight_decay=1e-4),
        "quick": Hyper("minkunet", {"ratio": 0.25}, epochs=3, batch_size=2, lr=0.05, weight_decay=1e-4,
                       val_frames=48),
    },
}


@dataclass(frozen=True)
class TrainConfig:
    """A training job. ``None`` hyperparameters come from the profile (:data:`PROFILES`)."""

    stage: str
    store: str
    out: str
    profile: str = "quick"
    model: str | None = None
    model_config: dict[str, Any] | None = None
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    seed: int = 0
    device: str = "auto"
    train_split: str = "train"
    val_split: str | None = "val"
    max_steps: int | None = None  # stop after this many optimiser steps in all (smoke tests)
    max_minutes: float | None = None  # stop after this much training time in all (equal budgets)
    optimizer: str | None = None  # "adam" or "sgd" instead of the stage's own (e.g. Adam for sparsity training)
    resume: bool = False
    workers: int = 0  # DataLoader worker processes
    jitter_from: str | None = None  # segmenter: detector checkpoint whose errors are measured
    jitter_std: tuple[float, float, float] | None = None  # segmenter: Gaussian errors in bins instead
    ray_workers: int = 0  # 0 = single process without Ray
    address: str | None = None  # Ray address for --ray-workers (None = embedded local Ray)
    threads: int = 0  # torch intra-op threads (0 = torch's default)
    progress: bool = True
    slim_lambda: float = 0.0  # network slimming: weight of the L1 penalty on every BatchNorm scale
    init: str | None = None  # start from this checkpoint's architecture and weights (fine-tuning)

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {self.stage!r}")
        if self.profile not in PROFILES[self.stage]:
            raise ValueError(f"profile must be one of {sorted(PROFILES[self.stage])}, got {self.profile!r}")
        for name in ("epochs", "batch_size", "max_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if self.lr is not None and not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        check_budget(self.max_minutes)
        if self.optimizer is not None and self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.max_minutes is not None and self.ray_workers:
            raise ValueError("--max-minutes is for single-process runs: Ray Train workers would stop at different "
                             "steps; use --max-steps with --ray-workers")
        if not self.slim_lambda >= 0:
            raise ValueError(f"slim_lambda must be >= 0, got {self.slim_lambda}")
        if self.ray_workers < 0 or self.workers < 0:
            raise ValueError(f"ray_workers and workers must be >= 0, got {self.ray_workers}, {self.workers}")
        if self.jitter_from and self.jitter_std:
            raise ValueError("give either jitter_from (a detector checkpoint) or jitter_std, not both")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")

    def hyper(self) -> Hyper:
        """The profile's hyperparameters with this config's overrides."""
        base = PROFILES[self.stage][self.profile]
        overrides = {name: getattr(self, name) for name in ("model", "epochs", "batch_size", "lr", "optimizer")
                     if getattr(self, name) is not None}
        if self.model_config is not None:
            overrides["model_config"] = dict(self.model_config)
        if self.jitter_std is not None:
            overrides["jitter_std"] = tuple(self.jitter_std)
        return dataclasses.replace(base, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown training config keys {sorted(unknown)}")
        data = dict(data)
        if data.get("jitter_std") is not None:
            data["jitter_std"] = tuple(data["jitter_std"])
        return cls(**data)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run it continues."""
        keep = ("stage", "store", "profile", "model", "model_config", "batch_size", "lr", "seed", "train_split",
                "jitter_from", "jitter_std", "slim_lambda", "init", "optimizer")
        return {k: v for k, v in self.to_dict().items() if k in keep}


def resolve_device(name: str) -> torch.device:
    """``auto`` -> CUDA when available, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


# --------------------------------------------------------------------------- data-parallel world
class World:
    """The single-process world: rank 0 of 1. The Ray Train world overrides these."""

    rank = 0
    size = 1

    def wrap(self, model: nn.Module) -> nn.Module:
        return model

    def report(self, metrics: dict[str, Any]) -> None:
        pass


class RayWorld(World):
    """A Ray Train worker: rank and size from the train context; DDP via ``prepare_model``."""

    def __init__(self) -> None:
        import ray.train

        context = ray.train.get_context()
        self.rank = context.get_world_rank()
        self.size = context.get_world_size()

    def wrap(self, model: nn.Module) -> nn.Module:
        import ray.train.torch

        return ray.train.torch.prepare_model(model, move_to_device=False)

    def report(self, metrics: dict[str, Any]) -> None:
        import ray.train

        ray.train.report({k: v for k, v in metrics.items() if isinstance(v, int | float)})


def unwrap(model: nn.Module) -> nn.Module:
    """The model inside a DistributedDataParallel wrapper (or the model itself)."""
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


# --------------------------------------------------------------------------- store helpers
@dataclass(frozen=True)
class StoreInfo:
    """What the trainer reads from a store's attributes."""

    path: str
    profile: RadarProfile
    class_names: tuple[str, ...]  # background first
    normalisation: dict[str, Any]  # mean, std (dB), mean_per_doppler, std_per_doppler (D values)

    @classmethod
    def read(cls, path: str | Path) -> StoreInfo:
        attrs = open_store(path).attrs.asdict()
        stats = attrs["normalisation"]
        normalisation = {"mean": float(stats["mean"]), "std": float(stats["std"]),
                         "mean_per_doppler": [float(v) for v in stats["mean_per_doppler"]],
                         "std_per_doppler": [float(v) for v in stats["std_per_doppler"]]}
        profile = get_profile(attrs["preset"])
        names = tuple(attrs.get("class_names") or profile.all_class_names)
        if len(names) != profile.num_classes:
            raise ValueError(f"store {path}: {len(names)} class names, preset {profile.name} has "
                             f"{profile.num_classes} classes")
        return cls(str(path), profile, names, normalisation)


def frame_centres(sample: dict[str, Any]) -> np.ndarray:
    """(N, 3) float64 (range, angle, Doppler) bins of a sample's objects (from its object table)."""
    n = int(sample["n_objects"])
    return sample["objects"][:n, CENTRE_COLUMNS].double().numpy()


def _subset(frames: int, limit: int) -> list[int]:
    """Evenly spread indices of ``limit`` of ``frames`` items (all when limit is 0 or larger)."""
    if not limit or limit >= frames:
        return list(range(frames))
    return sorted({int(i) for i in np.linspace(0, frames - 1, limit)})


# --------------------------------------------------------------------------- stage tasks
class StageTask:
    """What differs between the stages: data, model, loss, optimiser, validation, checkpoint extras."""

    stage: str = ""
    monitor: str = ""  # validation metric that picks model.pt (higher is better)

    def __init__(self, cfg: TrainConfig, hyper: Hyper, store: StoreInfo, run_dir: Path):
        self.cfg = cfg
        self.hyper = hyper
        self.store = store
        self.run_dir = run_dir

    def model_config(self) -> dict[str, Any]:
        return {"preset": self.store.profile.name, **self.hyper.model_config}

    def build_model(self) -> nn.Module:
        return create_model(self.hyper.model, **self.model_config())

    def prepare(self, rank: int) -> None:
        """One-off work before training (rank 0 writes files; every rank must end up with the same state)."""

    def train_dataset(self) -> Dataset:
        raise NotImplementedError

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        raise NotImplementedError

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def optimizer(self, params) -> torch.optim.Optimizer:
        raise NotImplementedError

    def scheduler(self, optimizer: torch.optim.Optimizer, steps_per_epoch: int) -> torch.optim.lr_scheduler.LRScheduler:
        raise NotImplementedError

    @property
    def steps_scheduler_per_batch(self) -> bool:
        return False

    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        return {}

    def extra(self) -> dict[str, Any]:
        return {}


class DetectorTask(StageTask):
    stage = "detector"
    monitor = "val_mAP"

    def dataset(self, split: str, flip_prob: float = 0.0) -> StoreDataset:
        """Frames of ``split`` with their log power in dB (normalised in :meth:`collate`)."""
        return StoreDataset(self.store.path, split, fields=("input", "objects"), normalise=False,
                            flip_prob=flip_prob, seed=self.cfg.seed)

    def train_dataset(self) -> Dataset:
        return self.dataset(self.cfg.train_split, self.hyper.flip_prob)

    def collate(self, samples: list[dict[str, Any]]) -> dict[str, Any]:
        """Input ``(B, D, R, A)`` normalised with the store's global mean and std (dB), exactly what
        :class:`models.erasenet.EraseNet` does at inference, and the centre targets."""
        grid = (self.store.profile.n_range, self.store.profile.n_angle)
        log_power = torch.stack([s["input"] for s in samples])
        stats = self.store.normalisation
        return {"input": (log_power - stats["mean"]) / stats["std"],
                "targets": build_centre_targets([frame_centres(s) for s in samples], grid)}

    def loss(self, model: nn.Module, batch: dict[str, Any], device: torch.device) -> dict[str, torch.Tensor]:
        outputs = model(batch["input"].to(device))
        targets = {k: v.to(device) for k, v in batch["targets"].items()}
        return unwrap(model).compute_loss(outputs, targets)

    def optimizer(self, params) -> torch.optim.Optimizer:
        return make_optimizer(self.hyper, params, default="adam")

    def scheduler(self, optimizer, steps_per_epoch):
        if self.hyper.step_every:
            return torch.optim.lr_scheduler.StepLR(optimizer, self.hyper.step_every, gamma=self.hyper.gamma)
        milestones = sorted({max(1, round(f * self.hyper.epochs)) for f in self.hyper.milestones})
        return torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones, gamma=self.hyper.gamma)

    @torch.no_grad()
    def validate(self, model: nn.Module, device: torch.device) -> dict[str, float]:
        if not self.cfg.val_split:
            return {}
        dataset = self.dataset(self.cfg.val_split)
        if len(dataset) == 0:
            return {}
        model.eval()
        profile = self.store.profile
        evaluator = DetectionEvaluator()
        losses = []
        indices = _subset(len(dataset), self.hyper.val_frames)
        for start in range(0, len(indices), 8):
            samples = [dataset[i] for i in indices[start:start + 8]]
            batch = self.collate(samples)
            outputs = model(batch["input"].to(device))
            targets = {k: v.to(device) for k, v in batch["targets"].items()}
            losses.append(float(model.compute_loss(outputs, targets)["total"]) * len(samples))
            for sample, det in zip(samples, model.decode(outputs, k=20, score_threshold=0.05), strict=True):
                det = {k: v.cpu().numpy().astype(np.float64) for k, v in det.items()}
                n = int(sample["n_objects"])
                table = sample["objects"][:n].double().numpy()
                evaluator.add(np.stack(profile.xy(det["range_bin"], det["angle_bin"]), axis=1), det["doppler_bin"],
                              det["score"], table[:, [COL["x"], COL["y"]]], table[:, COL["doppler_bin"]])
        model.train()
        summary = evaluator.summary()
        return {"val_loss": sum(losses) / len(indices), **{f"val_{k}": v for k, v in summary.items()}}


# ----- segmenter
@dataclass(frozen=True)
class SeedJitter:
    """Errors added to ground-truth centres (bins: range, angle, Doppler) to make training seeds.

    ``residuals`` (K, 3): measured detector errors (prediction - truth), resampled with replacement;
    empty means Gaussian errors of ``std`` (3,) bins.
    """

    residuals: np.ndarray
    std: tuple[float, float, float]
    source: str
    stats: dict[str, Any] = field(default_factory=dict)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) errors in bins."""
        if len(self.residuals):
            return self.residuals[rng.integers(0, len(self.residuals), size=n)]
        return rng.normal(0.0, 1.0, size=(n, 3)) * np.asarray(self.std)

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "std": list(self.std), "residuals": self.residuals.tolist(), **self.stats}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SeedJitter:
        stats = {k: v for k, v in data.items() if k not in ("source", "std", "residuals")}
        return cls(np.asarray(data["residuals"], np.float64).reshape(-1, 3), tuple(data["std"]), data["source"], stats)


def detector_centres(detector: nn.Module, inputs: torch.Tensor, *, score_threshold: float = 0.3,
                     k: int = 20) -> list[dict[str, np.ndarray]]:
    """Decoded centres of a batch of normalised inputs ``(B, D, R, A)``, as numpy dicts of (N,) arrays."""
    with torch.no_grad():
        outputs = detector(inputs)
        return [{name: v.cpu().numpy().astype(np.float64) for name, v in det.items()}
                for det in detector.decode(outputs, k=k, score_threshold=score_threshold)]


def measure_detector_errors(detector_path: str | Path, store: str | Path, split: str = "val", *,
                            score_threshold: float = 0.3, max_frames: int = 0,
                            device: torch.device | str = "cpu") -> SeedJitter:
    """Errors of a trained detector on a split: for each ground-truth object, the nearest detection
    within :data:`JITTER_MATCH_M` metres and Doppler bins gives a residual (prediction - truth, bins).
    Also reports the miss rate and false positives per frame (in ``stats``)."""
    checkpoint = load_checkpoint(detector_path)
    detector = checkpoint.build(device=device)
    profile = get_profile(checkpoint.preset)
    dataset = StoreDataset(store, split, fields=("input", "objects"), normalise=False)
    mean_db, std_db = checkpoint.normalisation["mean"], checkpoint.normalisation["std"]
    residuals, misses, truths, false_pos = [], 0, 0, 0
    indices = _subset(len(dataset), max_frames)
    for start in range(0, len(indices), 8):
        samples = [dataset[i] for i in indices[start:start + 8]]
        log_power = torch.stack([s["input"] for s in samples])  # (B, D, R, A) dB
        dets = detector_centres(detector, ((log_power - mean_db) / std_db).to(device),
                                score_threshold=score_threshold)
        for sample, det in zip(samples, dets, strict=True):
            truth = frame_centres(sample)
            pred = np.stack([det["range_bin"], det["angle_bin"], det["doppler_bin"]], axis=1)
            pred_xy = np.stack(profile.xy(pred[:, 0], pred[:, 1]), axis=1)
            truth_xy = np.stack(profile.xy(truth[:, 0], truth[:, 1]), axis=1)
            used = np.zeros(len(pred), bool)
            for t in range(len(truth)):
                dist = np.linalg.norm(pred_xy - truth_xy[t], axis=1)
                ok = (dist <= JITTER_MATCH_M) & (np.abs(pred[:, 2] - truth[t, 2]) < JITTER_MATCH_M) & ~used
                if ok.any():
                    j = np.flatnonzero(ok)[np.argmin(dist[ok])]
                    used[j] = True
                    residuals.append(pred[j] - truth[t])
                else:
                    misses += 1
            truths += len(truth)
            false_pos += int((~used).sum())
    residuals_arr = np.asarray(residuals, np.float64).reshape(-1, 3)
    std = tuple(float(v) for v in residuals_arr.std(axis=0)) if len(residuals_arr) else (1.0, 1.0, 0.5)
    stats = {"split": split, "frames": len(indices), "objects": truths, "matched": len(residuals_arr),
             "miss_rate": misses / max(truths, 1), "false_positives_per_frame": false_pos / max(len(indices), 1),
             "score_threshold": score_threshold, "match_m": JITTER_MATCH_M,
             "mean_bins": residuals_arr.mean(axis=0).tolist() if len(residuals_arr) else [0.0, 0.0, 0.0],
             "abs_p90_bins": np.percentile(np.abs(residuals_arr), 90, axis=0).tolist() if len(residuals_arr)
             else [0.0, 0.0, 0.0]}
    if not len(residuals_arr):
        raise ValueError(f"detector {detector_path} matched no object of split {split!r}: cannot measure its errors")
    return SeedJitter(residuals_arr, std, f"measured: {detector_path}", stats)


def sparse_input(model: nn.Module, batch: dict[str, Any], device: torch.device) -> SparseTensor | PointTensor:
    """The segmenter's input for a collated ROI batch: a SparseTensor, or a PointTensor for SPVCNN."""
    coords = batch["coords"].to(device)  # (N, 4) int64: batch, range, angle, Doppler bins
    feats = batch["features"].to(device)  # (N, 4)
    if isinstance(unwrap(model), SPVCNN):
        return PointTensor(coords[:, 0].contiguous(), coords[:, 1:].to(feats.dtype) + 0.5, feats)
    return SparseTensor(coords, feats)


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
                                   normalise=False, flip_prob=flip_prob, seed=seed)
        n_objects = open_store(store.path)["n_objects"][:]
        keep = [i for i, slot in enumerate(self.frames.frames) if n_objects[slot] > 0]
        self.indices = [keep[i] for i in _subset(len(keep), limit)]
        self.jitter = jitter
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, item: int) -> dict[str, Any]:
        sample = self.frames[self.indices[item]]
        log_power = sample["input"].permute(1, 2, 0).numpy()  # (R, A, D) dB
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


class SegmenterTask(StageTask):
    stage = "segmenter"
    monitor = "val_mIoU"

    def __init__(self, cfg: TrainConfig, hyper: Hyper, store: StoreInfo, run_dir: Path):
        super().__init__(cfg, hyper, store, run_dir)
        self.jitter: SeedJitter | None = None
        self.class_weights: torch.Tensor | None = None

    def prepare(self, rank: int) -> None:
        jitter_path = self.run_dir / "jitter.json"
        weights_path = self.run_dir / "class_weights.json"
        if jitter_path.is_file():  # resumed run, or written by rank 0 of this run
            self.jitter = SeedJitter.from_dict(json.loads(jitter_path.read_text()))
        elif self.cfg.jitter_from:
            self.jitter = measure_detector_errors(self.cfg.jitter_from, self.store.path,
                                                  self.cfg.val_split or self.cfg.train_split, max_frames=96)
        else:
            log.warning("no --jitter-from detector given: seeds jittered by Gaussian errors of std %s bins",
                        self.hyper.jitter_std)
            self.jitter = SeedJitter(np.zeros((0, 3)), self.hyper.jitter_std, "gaussian (assumed)")
        if weights_path.is_file():
            self.class_weights = torch.tensor(json.loads(weights_path.read_text())["weights"])
        else:
            self.class_weights = self._measure_class_weights()
        if rank == 0:
            jitter_path.write_text(json.dumps(self.jitter.to_dict()))
            weights_path.write_text(json.dumps({"weights": self.class_weights.tolist(),
                                                "classes": list(self.store.class_names)}))

    def _measure_class_weights(self, frames: int = 64) -> torch.Tensor:
        """``1 / sqrt(frequency)`` of each class among ROI voxels of up to ``frames`` training frames,
        normalised to mean 1 over the classes seen (unseen classes get the largest weight)."""
        dataset = RoiDataset(self.store, self.cfg.train_split, self.jitter, seed=self.cfg.seed, limit=frames)
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

    def collate(self, samples):
        return collate_roi(samples)

    def loss(self, model, batch, device):
        logits = model(sparse_input(model, batch, device))
        loss = nn.functional.cross_entropy(logits, batch["labels"].to(device), weight=self.class_weights.to(device))
        return {"ce": loss, "total": loss}

    def optimizer(self, params):
        return make_optimizer(self.hyper, params, default="sgd")

    def scheduler(self, optimizer, steps_per_epoch):
        total = max(1, self.hyper.epochs * steps_per_epoch)
        return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 0.5 * (1 + math.cos(math.pi * min(step, total)
                                                                                               / total)))

    @property
    def steps_scheduler_per_batch(self) -> bool:
        return True

    @torch.no_grad()
    def validate(self, model, device):
        if not self.cfg.val_split:
            return {}
        dataset = RoiDataset(self.store, self.cfg.val_split, self.jitter, seed=self.cfg.seed + 1,
                             limit=self.hyper.val_frames)
        if len(dataset) == 0:
            return {}
        model.eval()
        num_classes = self.store.profile.num_classes
        confusion = np.zeros((num_classes, num_classes), np.int64)
        recalls = []
        for start in range(0, len(dataset), 4):
            batch = collate_roi([dataset[i] for i in range(start, min(start + 4, len(dataset)))])
            pred = model(sparse_input(model, batch, device)).argmax(1).cpu().numpy()
            confusion += confusion_matrix(batch["labels"].numpy(), pred, num_classes)
            recalls += batch["recall"]
        model.train()
        # voxel-level mIoU over the ROI voxels (background included), seeds jittered like in training
        return {"val_mIoU": mean_iou(confusion), "val_roi_recall": float(np.mean(recalls))}

    def extra(self) -> dict[str, Any]:
        return {"jitter": {k: v for k, v in self.jitter.to_dict().items() if k != "residuals"},
                "class_weights": self.class_weights.tolist()}


TASKS: dict[str, type[StageTask]] = {"detector": DetectorTask, "segmenter": SegmenterTask}


# --------------------------------------------------------------------------- the loop
def _checkpoint(task: StageTask, model: nn.Module, extra: dict[str, Any]) -> Checkpoint:
    state = {k: v.detach().cpu().clone() for k, v in unwrap(model).state_dict().items()}
    return Checkpoint(model_name=task.hyper.model, config=task.model_config(), state_dict=state,
                      preset=task.store.profile.name, class_names=task.store.class_names,
                      normalisation=dict(task.store.normalisation),
                      extra={"stage": task.stage, "profile": task.cfg.profile, **task.extra(), **extra})


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def train_loop(cfg: TrainConfig, world: World | None = None) -> dict[str, Any]:
    """Train ``cfg`` in this process (rank ``world.rank`` of ``world.size``); returns the last epoch's metrics."""
    world = world or World()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    hyper = cfg.hyper()
    run_dir = Path(cfg.out)
    store = StoreInfo.read(cfg.store)
    init = load_checkpoint(cfg.init) if cfg.init else None
    if init is not None:  # the checkpoint's architecture (a pruned one carries its channels table)
        if init.preset != store.profile.name:
            raise ValueError(f"--init {cfg.init} is for preset {init.preset!r}, the store for {store.profile.name!r}")
        hyper = dataclasses.replace(hyper, model=init.model_name,
                                    model_config={k: v for k, v in init.config.items() if k != "preset"})
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    last_path, model_path = run_dir / "last.pt", run_dir / "model.pt"
    if world.rank == 0:
        run_dir.mkdir(parents=True, exist_ok=True)
        config_path = run_dir / "config.json"
        if last_path.exists() and not cfg.resume:
            raise FileExistsError(f"{run_dir} already holds a run (last.pt); pass --resume to continue it "
                                  "or choose another --out")
        if cfg.resume and config_path.is_file():
            saved = json.loads(config_path.read_text())
            saved.pop("resolved", None)
            before = TrainConfig.from_dict(saved).identity()
            if before != cfg.identity():
                changed = sorted(k for k in before if before[k] != cfg.identity()[k])
                raise ValueError(f"--resume: {run_dir} was trained with other settings ({', '.join(changed)})")
        config_path.write_text(json.dumps({**cfg.to_dict(), "resolved": dataclasses.asdict(hyper)}, indent=2))

    task = TASKS[cfg.stage](cfg, hyper, store, run_dir)
    task.prepare(world.rank)
    model = task.build_model().to(device)
    if init is not None:
        model.load_state_dict(init.state_dict)
    optimizer = task.optimizer(model.parameters())
    dataset = task.train_dataset()
    if len(dataset) < world.size * hyper.batch_size:
        raise ValueError(f"split {cfg.train_split!r} of {cfg.store} has {len(dataset)} usable frames, fewer than "
                         f"one batch of {hyper.batch_size} per worker ({world.size} workers)")
    sampler = DistributedSampler(dataset, num_replicas=world.size, rank=world.rank, shuffle=True, seed=cfg.seed,
                                 drop_last=True)
    loader = DataLoader(dataset, batch_size=hyper.batch_size, sampler=sampler, collate_fn=task.collate,
                        num_workers=cfg.workers, drop_last=True)  # drop_last: BatchNorm at P7 needs >= 2
    steps_per_epoch = len(loader)
    scheduler = task.scheduler(optimizer, steps_per_epoch)

    start_epoch, step, best, elapsed = 0, 0, -math.inf, 0.0
    if cfg.resume and last_path.is_file():
        state = load_checkpoint(last_path)
        model.load_state_dict(state.state_dict)
        optimizer.load_state_dict(state.extra["optimizer"])
        scheduler.load_state_dict(state.extra["scheduler"])
        start_epoch, step, best = int(state.extra["epoch"]), int(state.extra["step"]), float(state.extra["best"])
        elapsed = float(state.extra.get("elapsed_s", 0.0))
        log.info("resumed %s at epoch %d, step %d", run_dir, start_epoch, step)
    model = world.wrap(model)
    model.train()

    metrics: dict[str, Any] = {}
    budget = Budget(cfg.max_steps, cfg.max_minutes, spent_s=elapsed)
    for epoch in range(start_epoch, hyper.epochs):
        if budget.spent(step):
            break
        sampler.set_epoch(epoch)
        if hasattr(dataset, "set_epoch"):
            dataset.set_epoch(epoch)
        losses: dict[str, list[float]] = {}
        samples, started = 0, time.perf_counter()
        bar = tqdm(loader, desc=f"{cfg.stage} epoch {epoch + 1}/{hyper.epochs}", unit="batch", leave=False,
                   disable=not cfg.progress or world.rank != 0, dynamic_ncols=True)
        for batch in bar:
            named = task.loss(model, batch, device)
            if cfg.slim_lambda:  # network slimming: L1 on every BatchNorm scale
                named["slim_l1"] = cfg.slim_lambda * slimming_penalty(unwrap(model))
                named["total"] = named["total"] + named["slim_l1"]
            optimizer.zero_grad(set_to_none=True)
            named["total"].backward()
            optimizer.step()
            if task.steps_scheduler_per_batch:
                scheduler.step()
            step += 1
            samples += hyper.batch_size * world.size
            for name, value in named.items():
                losses.setdefault(name, []).append(float(value.detach()))
            rate = samples / max(time.perf_counter() - started, 1e-9)
            bar.set_postfix(loss=f"{_mean(losses['total'][-20:]):.4f}", frames_s=f"{rate:.1f}")
            if budget.spent(step):
                break
        bar.close()
        if not task.steps_scheduler_per_batch:
            scheduler.step()
        seconds = time.perf_counter() - started
        metrics = {"epoch": epoch + 1, "step": step, "lr": optimizer.param_groups[0]["lr"],
                   **{f"train_{k}": _mean(v) for k, v in losses.items()}, "seconds": seconds,
                   "frames_per_second": samples / max(seconds, 1e-9)}
        if world.rank == 0:
            started_val = time.perf_counter()
            metrics.update(task.validate(unwrap(model), device))
            metrics["seconds_validation"] = time.perf_counter() - started_val
            elapsed += time.perf_counter() - started
            metrics["elapsed_s"] = elapsed  # training + validation time of the whole run so far
            score = metrics.get(task.monitor, float("nan"))
            # without a validation score every epoch is "best": model.pt is then the latest weights
            improved = not math.isfinite(score) or score >= best
            if improved:
                best = score if math.isfinite(score) else best
                save_checkpoint(_checkpoint(task, model, {"epoch": epoch + 1, "step": step, "metrics": metrics}),
                                model_path)
            metrics["best"] = improved
            save_checkpoint(_checkpoint(task, model, {
                "epoch": epoch + 1, "step": step, "best": best, "elapsed_s": elapsed, "metrics": metrics,
                "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()}), last_path)
            with (run_dir / "metrics.jsonl").open("a") as fh:
                fh.write(json.dumps(metrics) + "\n")
            log.info("%s epoch %d: %s", cfg.stage, epoch + 1,
                     ", ".join(f"{k} {v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
        world.report(metrics)
    return metrics


# --------------------------------------------------------------------------- Ray Train
def _ray_worker(config: dict[str, Any]) -> None:
    """Ray Train's per-worker function: the same loop, in a data-parallel world."""
    torch.set_num_threads(max(1, int(config.get("threads", 1))))
    train_loop(TrainConfig.from_dict(config["cfg"]), RayWorld())


def run_ray_train(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg.ray_workers`` data-parallel workers under Ray Train's TorchTrainer (gloo on CPU, NCCL on GPU)."""
    import ray
    from ray.train import RunConfig, ScalingConfig
    from ray.train.torch import TorchConfig, TorchTrainer

    started_here = False
    if not ray.is_initialized():
        if cfg.address is None and not os.environ.get("RAY_ADDRESS"):
            os.environ.setdefault("RAY_AUTH_MODE", "disabled")
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
            ray.init(address="local", num_cpus=max(2, cfg.ray_workers), include_dashboard=False,
                     object_store_memory=RAY_OBJECT_STORE_BYTES, logging_level=logging.WARNING)
        else:
            ray.init(address=cfg.address, logging_level=logging.WARNING)
        started_here = True
    try:
        run_dir = Path(cfg.out).resolve()
        run_dir.mkdir(parents=True, exist_ok=True)
        use_gpu = resolve_device(cfg.device).type == "cuda"
        worker_cfg = dataclasses.replace(cfg, out=str(run_dir), store=str(Path(cfg.store).resolve()),
                                         device="cuda" if use_gpu else "cpu", ray_workers=0)
        trainer = TorchTrainer(
            _ray_worker,
            train_loop_config={"cfg": worker_cfg.to_dict(), "threads": 1},
            torch_config=TorchConfig(backend="nccl" if use_gpu else "gloo"),
            scaling_config=ScalingConfig(num_workers=cfg.ray_workers, use_gpu=use_gpu),
            run_config=RunConfig(name=f"train-{cfg.stage}", storage_path=str(run_dir / "ray")),
        )
        result = trainer.fit()
        if result.error is not None:
            raise result.error
        # rank 0 wrote every epoch's metrics; Ray's result keeps only what came with a Ray checkpoint
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        return json.loads(lines[-1]) if lines else {}
    finally:
        if started_here:
            ray.shutdown()


# --------------------------------------------------------------------------- job entry points
def main(cfg: TrainConfig) -> dict[str, Any]:
    """Run the job; returns the last epoch's metrics and where the run lives."""
    started = time.perf_counter()
    metrics = run_ray_train(cfg) if cfg.ray_workers else train_loop(cfg)
    return {"run": str(cfg.out), "checkpoint": str(Path(cfg.out) / "model.pt"),
            "seconds": time.perf_counter() - started, "metrics": metrics}


def export_checkpoint(source: str | Path, target: str | Path, *, float16: bool = True) -> Path:
    """Write a shippable copy of a training checkpoint: weights only (no optimiser state), floating
    tensors in float16 when ``float16`` (half the size; :meth:`Checkpoint.build` loads them back into the
    float32 model). Returns ``target``."""
    checkpoint = load_checkpoint(source)
    state = {k: (v.half() if float16 and v.is_floating_point() else v) for k, v in checkpoint.state_dict.items()}
    extra = {k: v for k, v in checkpoint.extra.items() if k not in ("optimizer", "scheduler")}
    extra["stored_dtype"] = "float16" if float16 else "float32"
    return save_checkpoint(dataclasses.replace(checkpoint, state_dict=state, extra=extra), target)


def build_parser(prog: str = "python -m pipelines.train") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="train a stage of ERASE-Net from a preprocessed store")
    parser.add_argument("stage", choices=STAGES)
    parser.add_argument("--model", help="registered model name (default: the profile's)")
    add_common_arguments(parser)
    parser.add_argument("--jitter-from", help="segmenter: detector checkpoint whose errors jitter the seeds")
    parser.add_argument("--jitter-std", type=float, nargs=3, metavar=("RANGE", "ANGLE", "DOPPLER"),
                        help="segmenter: Gaussian seed errors in bins instead")
    parser.add_argument("--ray-workers", type=int, default=0, help="data-parallel Ray Train workers (0: no Ray)")
    parser.add_argument("--address", help="Ray address (default: embedded local Ray)")
    parser.add_argument("--optimizer", choices=OPTIMIZERS,
                        help="instead of the stage's own (detector Adam, segmenter SGD), e.g. Adam for sparsity")
    return parser


def check_budget(max_minutes: float | None) -> None:
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"max_minutes must be > 0, got {max_minutes}")


class Budget:
    """When a run stops early: after ``max_steps`` optimiser steps or ``max_minutes`` of training in all
    (``spent_s``: time a resumed run had already used; measured from construction)."""

    def __init__(self, max_steps: int | None, max_minutes: float | None, *, spent_s: float = 0.0) -> None:
        self.max_steps = max_steps
        self.deadline = None if max_minutes is None else time.perf_counter() + 60.0 * max_minutes - spent_s

    def spent(self, step: int) -> bool:
        return ((self.max_steps is not None and step >= self.max_steps)
                or (self.deadline is not None and time.perf_counter() >= self.deadline))


def add_common_arguments(parser: argparse.ArgumentParser, *, profiles: Sequence[str] = ("quick", "paper")) -> None:
    """The options every trainer shares (this one and pipelines.train_baselines)."""
    parser.add_argument("--store", required=True, help="preprocessed store (zarr)")
    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument("--profile", choices=sorted(profiles), default="quick")
    parser.add_argument("--model-config", type=json.loads, help="builder keyword arguments as JSON")
    parser.add_argument("--epochs", type=int)
    parser.add_argument("--batch-size", type=int)
    parser.add_argument("--lr", type=float)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda, cuda:N")
    parser.add_argument("--train-split", default="train")
    parser.add_argument("--val-split", default="val", help="'none' to skip validation")
    parser.add_argument("--max-steps", type=int, help="stop after this many optimiser steps (smoke runs)")
    parser.add_argument("--max-minutes", type=float,
                        help="stop after this many minutes of training (validation included; equal budgets)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    parser.add_argument("--workers", type=int, default=0, help="DataLoader worker processes")
    parser.add_argument("--slim-lambda", type=float, nargs="?", const=1e-4, default=0.0,
                        help="network slimming: L1 weight on every BatchNorm scale (1e-4 when given alone)")
    parser.add_argument("--init", help="start from this checkpoint's architecture and weights (e.g. a pruned one)")
    parser.add_argument("--no-progress", action="store_true")


def common_config(args: argparse.Namespace) -> dict[str, Any]:
    """The config fields of :func:`add_common_arguments`' options."""
    return dict(store=args.store, out=args.out, profile=args.profile, model_config=args.model_config,
                epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed, device=args.device,
                train_split=args.train_split, val_split=None if args.val_split.lower() == "none" else args.val_split,
                max_steps=args.max_steps, max_minutes=args.max_minutes, threads=args.threads, resume=args.resume,
                workers=args.workers, progress=not args.no_progress,
                slim_lambda=args.slim_lambda, init=args.init)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(
        stage=args.stage, model=args.model, jitter_from=args.jitter_from,
        jitter_std=tuple(args.jitter_std) if args.jitter_std else None, ray_workers=args.ray_workers,
        address=args.address, optimizer=args.optimizer, **common_config(args))


def parse_args(argv: Sequence[str] | None = None, *, prog: str = "python -m pipelines.train") -> TrainConfig:
    return config_from_args(build_parser(prog).parse_args(argv))


def run_cli(argv: Sequence[str] | None = None, *, prog: str = "python -m pipelines.train") -> dict[str, Any]:
    """``STAGE ...`` trains (see :func:`build_parser`); ``export SOURCE TARGET [--float32]`` writes a
    shippable checkpoint (:func:`export_checkpoint`). Returns what the command produced."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["export"]:
        parser = argparse.ArgumentParser(prog=f"{prog} export", description="a shippable copy of a checkpoint")
        parser.add_argument("source")
        parser.add_argument("target")
        parser.add_argument("--float32", action="store_true", help="keep float32 weights (default float16)")
        args = parser.parse_args(argv[1:])
        target = export_checkpoint(args.source, args.target, float16=not args.float32)
        return {"checkpoint": str(target), "bytes": target.stat().st_size}
    return main(parse_args(argv, prog=prog))


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    print(json.dumps(run_cli(), indent=2, default=str))
