"""Training and scoring of the 2-D baselines (U-Net per view, TMVA-Net, SMVA-Net; SPEC section 9).

The job is ``parse_args() -> main(cfg) -> dict``::

    python -m pipelines.train_baselines tmvanet --store STORE.zarr --out runs/tmva [--profile quick|paper]
    python -m pipelines.train_baselines unet --view ra --store STORE.zarr --out runs/unet-ra [--resume]

Data: :class:`pipelines.views.ViewDataset` (RD/RA/AD views scaled by the train split's min/max; TMVA-Net
reads the target frame and the 4 before it in its sequence, so the first 4 frames of each sequence
are not used, as in the reference). Loss: :class:`models.baselines.losses.MultiViewLoss` (per view
0.5 x weighted CE + 5 x soft Dice, plus 5 x coherence for the two-view networks), class weights the
normalised inverse pixel frequencies of the train split's RD and RA masks. Optimiser as in the reference:
Adam, learning rate multiplied by ``lr_decay`` every ``lr_step`` epochs; random left-right (angle)
mirroring of whole windows.

Profiles (:data:`PROFILES`): ``paper`` is the reference's recipe (300 epochs, batch 6, Adam 1e-4,
x0.9 every 20 epochs, flips); ``quick`` is a CPU budget for the ``small`` preset (not tuned yet).

Network slimming as in :mod:`pipelines.train`: ``--slim-lambda [L]`` (L1 on every BatchNorm scale, 1e-4 when
given alone) and ``--init CKPT`` (start from a checkpoint's architecture and weights, e.g. a pruned one; the
paper fine-tunes the baselines at lr 1e-5).

The run directory follows :mod:`pipelines.train`: ``config.json`` (with the resolved hyperparameters),
``metrics.jsonl`` (one line per epoch), ``last.pt`` (weights, optimiser, scheduler: ``--resume``),
``model.pt`` (the epoch with the best validation mIoU, mean over the predicted views), all
:class:`models.checkpoint.Checkpoint`; the view scaling is the checkpoint's ``normalisation`` and the
class weights, frame count and views are in its ``extra``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from models.baselines.losses import MultiViewLoss, class_weights_from_counts
from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.registry import create_model
from models.slimming import slimming_penalty
from pipelines.train import Budget, StoreInfo, add_common_arguments, check_budget, common_config, resolve_device
from pipelines.views import ViewDataset, ViewStats, collate_views, masks_of, model_inputs, view_class_counts
from radar.metrics import confusion_matrix, iou_per_class, mean_iou

log = logging.getLogger(__name__)

STAGE = "baseline"
UNET_MODELS = ("unet", "unet_tiny")
MULTI_VIEW_MODELS = ("tmvanet", "smvanet", "tmvanet_tiny", "smvanet_tiny")
MODELS = UNET_MODELS + MULTI_VIEW_MODELS


@dataclass(frozen=True)
class BaselineHyper:
    """Hyperparameters of a baseline run (every field may be overridden)."""

    epochs: int
    batch_size: int
    lr: float
    lr_decay: float = 0.9  # ExponentialLR factor ...
    lr_step: int = 20  # ... applied every this many epochs
    flip_prob: float = 0.5
    val_frames: int = 0  # validation windows per epoch (evenly spread; 0 = all)


PROFILES: dict[str, BaselineHyper] = {
    "paper": BaselineHyper(epochs=300, batch_size=6, lr=1e-4, lr_decay=0.9, lr_step=20),
    "quick": BaselineHyper(epochs=8, batch_size=4, lr=3e-4, lr_decay=0.5, lr_step=4, val_frames=48),
}


@dataclass(frozen=True)
class BaselineConfig:
    """A baseline training job. ``None`` hyperparameters come from the profile (:data:`PROFILES`)."""

    model: str
    store: str
    out: str
    profile: str = "quick"
    view: str | None = None  # U-Net only: "ra" or "rd"
    model_config: dict[str, Any] | None = None  # extra builder keyword arguments
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    seed: int = 0
    device: str = "auto"
    train_split: str = "train"
    val_split: str | None = "val"
    max_steps: int | None = None  # stop after this many optimiser steps in all (smoke tests)
    max_minutes: float | None = None  # stop after this much training time in all (equal budgets)
    threads: int = 0  # torch intra-op threads (0 = torch's default)
    resume: bool = False
    workers: int = 0
    progress: bool = True
    slim_lambda: float = 0.0  # network slimming: weight of the L1 penalty on every BatchNorm scale
    init: str | None = None  # start from this checkpoint's architecture and weights (fine-tuning)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {sorted(PROFILES)}, got {self.profile!r}")
        if self.model in UNET_MODELS and self.view not in ("ra", "rd"):
            raise ValueError(f"a U-Net is trained on one view: view must be 'ra' or 'rd', got {self.view!r}")
        if self.model not in UNET_MODELS and self.view is not None:
            raise ValueError(f"{self.model} predicts both RA and RD: give no view, got {self.view!r}")
        for name in ("epochs", "batch_size", "max_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if self.lr is not None and not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        check_budget(self.max_minutes)
        if not self.slim_lambda >= 0:
            raise ValueError(f"slim_lambda must be >= 0, got {self.slim_lambda}")

    def hyper(self) -> BaselineHyper:
        overrides = {name: getattr(self, name) for name in ("epochs", "batch_size", "lr") if getattr(self, name)}
        return dataclasses.replace(PROFILES[self.profile], **overrides)

    def builder_config(self, preset: str) -> dict[str, Any]:
        """Keyword arguments of the registered builder (what the checkpoint stores)."""
        config: dict[str, Any] = {"preset": preset, **(self.model_config or {})}
        if self.view is not None:
            config["view"] = self.view
        return config

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BaselineConfig:
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown baseline config keys {sorted(unknown)}")
        return cls(**data)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run it continues."""
        keep = ("model", "store", "profile", "view", "model_config", "batch_size", "lr", "seed", "train_split",
                "slim_lambda", "init")
        return {k: v for k, v in self.to_dict().items() if k in keep}


def predicted_views(model: nn.Module) -> tuple[str, ...]:
    """The views a baseline predicts: its own for a U-Net, ``("rd", "ra")`` otherwise."""
    view = getattr(model, "view", None)
    return (view,) if view is not None else ("rd", "ra")


def class_weights(store: str | Path, split: str, views: Sequence[str]) -> dict[str, torch.Tensor]:
    """Per view (C,) weights from the split's mask pixel counts (:func:`class_weights_from_counts`)."""
    counts = view_class_counts(store, split)
    return {view: class_weights_from_counts(counts[view]) for view in views}


@torch.no_grad()
def score_baseline(model: nn.Module, dataset: ViewDataset, *, num_classes: int, loss_fn: MultiViewLoss | None = None,
                   batch_size: int = 4, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Segmentation scores of a baseline over every window of ``dataset`` (model put in eval mode).

    Returns ``frames`` (windows scored), per predicted view ``confusion_{view}`` ((C, C) list, rows truth),
    ``iou_{view}`` (per class, NaN for a class in neither truth nor prediction), ``mIoU_{view}``, and
    ``mIoU`` (mean over the predicted views); with ``loss_fn`` also ``loss`` (mean total per window).
    """
    model.eval()
    views = predicted_views(model)
    confusion = {view: np.zeros((num_classes, num_classes), np.int64) for view in views}
    loss_sum = 0.0
    for start in range(0, len(dataset), batch_size):
        batch = collate_views([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        outputs = model(*model_inputs(model, batch, device))
        masks = masks_of(batch, device)
        if loss_fn is not None:
            loss_sum += float(loss_fn(outputs, masks)["total"]) * len(batch["frame"])
        for view in views:
            confusion[view] += confusion_matrix(masks[view].cpu().numpy(), outputs[view].argmax(1).cpu().numpy(),
                                                num_classes)
    result: dict[str, Any] = {"frames": len(dataset)}
    for view in views:
        result[f"confusion_{view}"] = confusion[view].tolist()
        result[f"iou_{view}"] = iou_per_class(confusion[view]).tolist()
        result[f"mIoU_{view}"] = mean_iou(confusion[view])
    result["mIoU"] = float(np.mean([result[f"mIoU_{view}"] for view in views])) if len(dataset) else float("nan")
    if loss_fn is not None and len(dataset):
        result["loss"] = loss_sum / len(dataset)
    return result


def load_baseline(path: str | Path, *, device: str | torch.device = "cpu") -> tuple[nn.Module, Checkpoint, ViewStats]:
    """A trained baseline (eval mode), its checkpoint and the view scaling it was trained with."""
    checkpoint = load_checkpoint(path)
    if checkpoint.extra.get("stage") != STAGE:
        raise ValueError(f"{path}: not a baseline checkpoint (stage {checkpoint.extra.get('stage')!r})")
    return checkpoint.build(device=device), checkpoint, ViewStats.from_dict(checkpoint.normalisation)


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def train_baseline(cfg: BaselineConfig) -> dict[str, Any]:
    """Train ``cfg`` in this process; returns the last epoch's metrics (the run directory holds the rest)."""
    hyper = cfg.hyper()
    run_dir = Path(cfg.out)
    store = StoreInfo.read(cfg.store)
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    last_path, model_path, config_path = run_dir / "last.pt", run_dir / "model.pt", run_dir / "config.json"
    run_dir.mkdir(parents=True, exist_ok=True)
    if last_path.exists() and not cfg.resume:
        raise FileExistsError(f"{run_dir} already holds a run (last.pt); pass --resume to continue it or choose "
                              "another --out")
    if cfg.resume and config_path.is_file():
        before = BaselineConfig.from_dict({k: v for k, v in json.loads(config_path.read_text()).items()
                                           if k != "resolved"}).identity()
        if before != cfg.identity():
            changed = sorted(k for k in before if before[k] != cfg.identity()[k])
            raise ValueError(f"--resume: {run_dir} was trained with other settings ({', '.join(changed)})")
    config_path.write_text(json.dumps({**cfg.to_dict(), "resolved": dataclasses.asdict(hyper)}, indent=2))

    builder_config = cfg.builder_config(store.profile.name)
    init = load_checkpoint(cfg.init) if cfg.init else None
    if init is not None:  # the checkpoint's architecture (a pruned one carries its channels table)
        if init.model_name != cfg.model or init.preset != store.profile.name:
            raise ValueError(f"--init {cfg.init} holds {init.model_name} for preset {init.preset!r}, not "
                             f"{cfg.model} for {store.profile.name!r}")
        builder_config = dict(init.config)
    model = create_model(cfg.model, **builder_config).to(device)
    if init is not None:
        model.load_state_dict(init.state_dict)
    views = predicted_views(model)
    stats = ViewStats.from_store(cfg.store, cfg.train_split)
    weights = class_weights(cfg.store, cfg.train_split, views)
    loss_fn = MultiViewLoss(weights).to(device)
    dataset = ViewDataset(cfg.store, cfg.train_split, n_frames=model.n_frames, stats=stats,
                          flip_prob=hyper.flip_prob, seed=cfg.seed)
    if len(dataset) < hyper.batch_size:
        raise ValueError(f"split {cfg.train_split!r} of {cfg.store} has {len(dataset)} usable frames for "
                         f"{model.n_frames}-frame windows, fewer than one batch of {hyper.batch_size}")
    val_set = (ViewDataset(cfg.store, cfg.val_split, n_frames=model.n_frames, stats=stats, limit=hyper.val_frames)
               if cfg.val_split else None)
    optimizer = torch.optim.Adam(model.parameters(), lr=hyper.lr)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=hyper.lr_decay)
    extra_static = {"stage": STAGE, "profile": cfg.profile, "n_frames": model.n_frames, "views": list(views),
                    "class_weights": {view: w.tolist() for view, w in weights.items()},
                    "train_frames": len(dataset)}

    def checkpoint(extra: dict[str, Any]) -> Checkpoint:
        state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
        return Checkpoint(model_name=cfg.model, config=builder_config, state_dict=state, preset=store.profile.name,
                          class_names=store.class_names, normalisation=stats.to_dict(),
                          extra={**extra_static, **extra})

    start_epoch, step, best, elapsed = 0, 0, -math.inf, 0.0
    if cfg.resume and last_path.is_file():
        state = load_checkpoint(last_path)
        model.load_state_dict(state.state_dict)
        optimizer.load_state_dict(state.extra["optimizer"])
        scheduler.load_state_dict(state.extra["scheduler"])
        start_epoch, step, best = int(state.extra["epoch"]), int(state.extra["step"]), float(state.extra["best"])
        elapsed = float(state.extra.get("elapsed_s", 0.0))
        log.info("resumed %s at epoch %d, step %d", run_dir, start_epoch, step)

    metrics: dict[str, Any] = {}
    budget = Budget(cfg.max_steps, cfg.max_minutes, spent_s=elapsed)
    for epoch in range(start_epoch, hyper.epochs):
        if budget.spent(step):
            break
        dataset.set_epoch(epoch)
        order = np.random.default_rng([cfg.seed, epoch]).permutation(len(dataset)).tolist()  # same on resume
        loader = DataLoader(dataset, batch_size=hyper.batch_size, sampler=order, collate_fn=collate_views,
                            num_workers=cfg.workers, drop_last=True)
        model.train()
        losses: dict[str, list[float]] = {}
        samples, started = 0, time.perf_counter()
        bar = tqdm(loader, desc=f"{cfg.model} epoch {epoch + 1}/{hyper.epochs}", unit="batch", leave=False,
                   disable=not cfg.progress, dynamic_ncols=True)
        for batch in bar:
            named = loss_fn(model(*model_inputs(model, batch, device)), masks_of(batch, device))
            if cfg.slim_lambda:  # network slimming: L1 on every BatchNorm scale
                named["slim_l1"] = cfg.slim_lambda * slimming_penalty(model)
                named["total"] = named["total"] + named["slim_l1"]
            optimizer.zero_grad(set_to_none=True)
            named["total"].backward()
            optimizer.step()
            step += 1
            samples += len(batch["frame"])
            for name, value in named.items():
                losses.setdefault(name, []).append(float(value.detach()))
            bar.set_postfix(loss=f"{_mean(losses['total'][-20:]):.4f}")
            if budget.spent(step):
                break
        bar.close()
        if (epoch + 1) % hyper.lr_step == 0:
            scheduler.step()
        seconds = time.perf_counter() - started
        metrics = {"epoch": epoch + 1, "step": step, "lr": optimizer.param_groups[0]["lr"],
                   **{f"train_{k}": _mean(v) for k, v in losses.items()}, "seconds": seconds,
                   "frames_per_second": samples / max(seconds, 1e-9)}
        if val_set is not None and len(val_set):
            started_val = time.perf_counter()
            scores = score_baseline(model, val_set, num_classes=store.profile.num_classes, loss_fn=loss_fn,
                                    device=device)
            metrics.update({f"val_{k}": v for k, v in scores.items() if not k.startswith(("confusion", "iou"))})
            metrics["seconds_validation"] = time.perf_counter() - started_val
        elapsed += time.perf_counter() - started
        metrics["elapsed_s"] = elapsed  # training + validation time of the whole run so far
        score = metrics.get("val_mIoU", float("nan"))
        improved = not math.isfinite(score) or score >= best  # no validation: model.pt = latest weights
        if improved:
            best = score if math.isfinite(score) else best
            save_checkpoint(checkpoint({"epoch": epoch + 1, "step": step, "metrics": metrics}), model_path)
        metrics["best"] = improved
        save_checkpoint(checkpoint({"epoch": epoch + 1, "step": step, "best": best, "elapsed_s": elapsed,
                                    "metrics": metrics,
                                    "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()}),
                        last_path)
        with (run_dir / "metrics.jsonl").open("a") as fh:
            fh.write(json.dumps(metrics) + "\n")
        log.info("%s epoch %d: %s", cfg.model, epoch + 1,
                 ", ".join(f"{k} {v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
    return metrics


def main(cfg: BaselineConfig) -> dict[str, Any]:
    """Run the job; returns the last epoch's metrics and where the run lives."""
    started = time.perf_counter()
    metrics = train_baseline(cfg)
    return {"run": str(cfg.out), "checkpoint": str(Path(cfg.out) / "model.pt"),
            "seconds": time.perf_counter() - started, "metrics": metrics}


def build_parser(prog: str = "python -m pipelines.train_baselines") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="train a 2-D baseline (U-Net, TMVA-Net, SMVA-Net)")
    parser.add_argument("model", choices=MODELS)
    parser.add_argument("--view", choices=("ra", "rd"), help="U-Net only: the view it segments")
    add_common_arguments(parser, profiles=PROFILES)
    return parser


def config_from_args(args: argparse.Namespace) -> BaselineConfig:
    return BaselineConfig(model=args.model, view=args.view, **common_config(args))


def parse_args(argv: Sequence[str] | None = None, *,
               prog: str = "python -m pipelines.train_baselines") -> BaselineConfig:
    return config_from_args(build_parser(prog).parse_args(argv))


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    print(json.dumps(main(parse_args()), indent=2, default=str))
