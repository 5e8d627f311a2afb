"""One training config for every stage, the recipes' hyperparameters as data, and one override rule:
a config field that is not None replaces the recipe's value.

Recipes (:data:`RECIPES`): ``paper`` is the paper's (detector: Adam 1e-4 divided by 10 every
10 epochs, 300 epochs; segmenter: SGD from 0.24 with cosine decay, 300 epochs; baselines: the
reference's Adam 1e-4 x0.9 every 20 epochs, batch 6); ``quick`` converges on a 2-core CPU on the
``small`` preset (detector 12 epochs, segmenter MinkUNet ratio 0.25 for 3 epochs, baselines 8 epochs); ``crops``
trains paper-size radars (``carrada``) on a CPU: the detector on range x angle windows, the segmenter as ``quick``.
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
from dataclasses import dataclass
from typing import Any

from models.capabilities import Stage
from pipelines.jobs import always, cap, smoke

log = logging.getLogger(__name__)

OPTIMIZERS = ("adam", "sgd")
SCHEDULES = ("step", "cosine")  # step: per epoch (step_every or milestones); cosine: per optimiser step

DEFAULT_JITTER_STD = (1.0, 1.0, 0.5)
"""Gaussian seed errors (range, angle, Doppler bins) of segmenter training when no detector measures them."""


@dataclass(frozen=True)
class Hyper:
    """Hyperparameters of one stage under one recipe (every field may be overridden)."""

    model: str  # registered model name ("" for the baselines: the command names it)
    model_config: dict[str, Any]
    epochs: int
    batch_size: int
    lr: float
    optimizer: str = "adam"  # "adam", or "sgd" (Nesterov momentum)
    weight_decay: float = 0.0
    momentum: float = 0.9  # SGD only
    schedule: str = "step"
    milestones: tuple[float, ...] = ()  # step: fractions of the epochs where the lr is multiplied by gamma
    step_every: int = 0  # step: or every this many epochs (0 = use milestones)
    gamma: float = 0.1
    flip_prob: float = 0.5
    val_frames: int = 0  # frames (windows) of the validation split scored per epoch, evenly spread (0 = all)
    jitter_std: tuple[float, float, float] = DEFAULT_JITTER_STD  # segmenter, bins, when no detector is given
    lovasz_weight: float = 0.0  # segmenter: weight of the Lovasz-softmax term beside weighted cross entropy
    class_weights: tuple[float, ...] = ()  # detector: the focal loss's weight at each foreground class's centres
    history_drop: float = 0.25  # detector reading history (model_config history_frames): share trained on one cube
    crop: tuple[int, ...] = ()  # detector: train on (range, angle) windows of this many bins (): whole frames)
    crop_object_share: float = 0.8  # detector crops: the share of windows drawn around an object (the rest clutter)
    channels_last: bool = False  # detector: NHWC activations (faster window steps: benchmarks.detector_crops)


RECIPES: dict[str, dict[str, Hyper]] = {
    "detector": {
        # The paper: Adam, 1e-4, divided by 10 every 10 epochs, 300 epochs (read literally).
        "paper": Hyper("centre_detector", {}, epochs=300, batch_size=16, lr=1e-4, step_every=10),
        "quick": Hyper("centre_detector", {}, epochs=12, batch_size=8, lr=2e-3, milestones=(0.67, 0.88),
                       val_frames=96),
        # Paper-size radars on a CPU: 64 x 128 (range x angle) windows, an eighth of a 256 x 256 frame
        # (docs/guides/carrada-cpu.md); the 12-channel Doppler compression of the shipped small detector.
        "crops": Hyper("centre_detector", {"doppler_channels": 12}, epochs=12, batch_size=8, lr=2e-3,
                       milestones=(0.67, 0.88), val_frames=48, crop=(64, 128), channels_last=True),
    },
    "segmenter": {
        "paper": Hyper("minkunet", {"ratio": 0.37}, epochs=300, batch_size=8, lr=0.24, optimizer="sgd",
                       weight_decay=1e-4, schedule="cosine"),
        "quick": Hyper("minkunet", {"ratio": 0.25}, epochs=3, batch_size=2, lr=0.05, optimizer="sgd",
                       weight_decay=1e-4, schedule="cosine", val_frames=48),
        "crops": Hyper("minkunet", {"ratio": 0.25}, epochs=3, batch_size=2, lr=0.05, optimizer="sgd",
                       weight_decay=1e-4, schedule="cosine", val_frames=24),
    },
    "baseline": {
        "paper": Hyper("", {}, epochs=300, batch_size=6, lr=1e-4, step_every=20, gamma=0.9),
        "quick": Hyper("", {}, epochs=8, batch_size=4, lr=3e-4, step_every=4, gamma=0.5, val_frames=48),
    },
}


def _unmeasured(detector: str | None) -> None:
    """Smoke rule of ``jitter_from``: a detector trained for smoke-sized steps matches nothing to measure."""
    if detector:
        log.warning("smoke mode: the errors of --jitter-from %s are not measured; seeds get Gaussian errors, as "
                    "with --jitter-std", detector)


def check_budget(max_minutes: float | None) -> None:
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"max_minutes must be > 0, got {max_minutes}")


@dataclass(frozen=True)
class TrainConfig:
    """A training job of any stage. ``None`` hyperparameters come from the recipe (:data:`RECIPES`)."""

    stage: str
    store: str
    out: str
    recipe: str = "quick"
    model: str | None = None
    view: str | None = None  # one-view models (U-Net): "ra" or "rd"
    model_config: dict[str, Any] | None = None  # extra builder keyword arguments
    epochs: int | None = smoke(None, cap(1, fill=True))
    batch_size: int | None = smoke(None, cap(2, fill=True))
    lr: float | None = None
    optimizer: str | None = None  # "adam" or "sgd" instead of the recipe's (e.g. Adam for sparsity training)
    seed: int = 0
    device: str = "auto"
    train_split: str = "train"
    val_split: str | None = "val"
    max_steps: int | None = smoke(None, cap(2, fill=True))  # stop after this many optimiser steps in all
    max_minutes: float | None = None  # stop after this much training time in all (equal budgets)
    resume: bool = False
    workers: int = 0  # DataLoader worker processes
    jitter_from: str | None = smoke(None, _unmeasured)  # segmenter: detector checkpoint whose errors are measured
    jitter_std: tuple[float, float, float] | None = None  # segmenter: Gaussian errors in bins instead
    ray_workers: int = 0  # 0 = single process without Ray
    address: str | None = None  # Ray address for --ray-workers (None = embedded local Ray)
    threads: int = smoke(0, always(1))  # torch intra-op threads (0 = torch's default)
    progress: bool = True
    slim_lambda: float = 0.0  # network slimming: weight of the L1 penalty on every BatchNorm scale
    init: str | None = None  # start from this checkpoint's architecture and weights (fine-tuning)
    lovasz_weight: float | None = None  # segmenter: Lovasz-softmax beside the weighted cross entropy
    class_weights: tuple[float, ...] | None = None  # detector: focal weight per foreground class at its centres
    val_frames: int | None = None  # validation frames per epoch instead of the recipe's (0 = all)
    curve_every: int = 0  # validate every this many steps too, into curve.jsonl (learning curves; 0 = off)
    crop: tuple[int, int] | None = None  # detector: (range, angle) window in bins instead of the recipe's

    def __post_init__(self) -> None:
        if self.stage not in tuple(Stage):
            raise ValueError(f"stage must be one of {[str(s) for s in Stage]}, got {self.stage!r}")
        if self.recipe not in RECIPES[self.stage]:
            raise ValueError(f"recipe must be one of {sorted(RECIPES[self.stage])}, got {self.recipe!r}")
        for name in ("epochs", "batch_size", "max_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        if self.stage == "detector" and self.batch_size == 1:  # BatchNorm at the 1x1 deepest level needs 2 frames
            raise ValueError("--batch-size must be >= 2 for the detector: the BatchNorm of its deepest BiFPN level "
                             "(one cell per frame) needs at least 2 values per channel")
        if self.lr is not None and not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        check_budget(self.max_minutes)
        if self.optimizer is not None and self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.max_minutes is not None and self.ray_workers:
            raise ValueError("--max-minutes is for single-process runs: Ray Train workers would stop at different "
                             "steps; use --max-steps with --ray-workers")
        if self.curve_every < 0:
            raise ValueError(f"curve_every must be >= 0, got {self.curve_every}")
        if self.val_frames is not None and self.val_frames < 0:
            raise ValueError(f"val_frames must be >= 0, got {self.val_frames}")
        if self.lovasz_weight is not None and not self.lovasz_weight >= 0:
            raise ValueError(f"lovasz_weight must be >= 0, got {self.lovasz_weight}")
        if self.lovasz_weight and self.stage != "segmenter":
            raise ValueError(f"lovasz_weight is a segmenter loss, not for the {self.stage} stage")
        if self.class_weights is not None and (self.stage != "detector" or not all(w > 0 for w in self.class_weights)):
            raise ValueError(f"class_weights are positive weights of the detector's centre loss, got "
                             f"{self.class_weights} for the {self.stage} stage")
        if self.crop is not None and (self.stage != "detector" or len(self.crop) != 2
                                      or not all(int(n) > 0 for n in self.crop)):
            raise ValueError(f"crop is the detector's (range, angle) window in bins, two positive numbers, got "
                             f"{self.crop} for the {self.stage} stage")
        if not self.slim_lambda >= 0:
            raise ValueError(f"slim_lambda must be >= 0, got {self.slim_lambda}")
        if self.ray_workers < 0 or self.workers < 0:
            raise ValueError(f"ray_workers and workers must be >= 0, got {self.ray_workers}, {self.workers}")
        if self.jitter_from and self.jitter_std:
            raise ValueError("give either jitter_from (a detector checkpoint) or jitter_std, not both")
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        if self.stage == "baseline" and not self.model:
            raise ValueError("a baseline run names its model (unet, tmvanet, smvanet, or a _tiny variant)")
        self._check_view()

    def _check_view(self) -> None:
        """A one-view model (its builder takes ``view``) needs a view; a multi-view one takes none."""
        from models.registry import get_builder  # torch: not loaded to declare the options (radarseg train --help)

        name = self.hyper().model
        takes_view = "view" in inspect.signature(get_builder(name)).parameters
        if takes_view and self.view not in ("ra", "rd"):
            raise ValueError(f"{name} is trained on one view: view must be 'ra' or 'rd', got {self.view!r}")
        if not takes_view and self.view is not None:
            raise ValueError(f"{name} takes no view (it predicts what it predicts), got {self.view!r}")

    def hyper(self) -> Hyper:
        """The recipe's hyperparameters with every override that is not None (another ``model`` without a
        ``model_config`` is built with its builder's defaults: the recipe's arguments belong to its own model)."""
        base = RECIPES[self.stage][self.recipe]
        overrides = {name: getattr(self, name) for name in ("model", "epochs", "batch_size", "lr", "optimizer",
                                                             "lovasz_weight", "val_frames")
                     if getattr(self, name) is not None}
        if self.model_config is not None:
            overrides["model_config"] = dict(self.model_config)
        elif self.model is not None and self.model != base.model:  # the recipe's builder arguments are its model's
            overrides["model_config"] = {}
        if self.jitter_std is not None:
            overrides["jitter_std"] = tuple(self.jitter_std)
        if self.class_weights is not None:
            overrides["class_weights"] = tuple(self.class_weights)
        if self.crop is not None:
            overrides["crop"] = tuple(self.crop)
        return dataclasses.replace(base, **overrides)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        if "profile" in data and "recipe" not in data:  # a run saved before the recipe had its name
            data = {("recipe" if key == "profile" else key): value for key, value in data.items()}
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown training config keys {sorted(unknown)}")
        data = dict(data)
        for key in ("jitter_std", "class_weights", "crop"):
            if data.get(key) is not None:
                data[key] = tuple(data[key])
        return cls(**data)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run it continues."""
        keep = ("stage", "store", "recipe", "model", "view", "model_config", "batch_size", "lr", "seed",
                "train_split", "jitter_from", "jitter_std", "slim_lambda", "init", "optimizer", "lovasz_weight",
                "class_weights", "crop")
        return {k: v for k, v in self.to_dict().items() if k in keep}


RECIPE_NAMES = tuple(dict.fromkeys(name for stage in RECIPES.values() for name in stage))
"""Every recipe name, for the command line (a stage without one refuses it: :meth:`TrainConfig.__post_init__`)."""
