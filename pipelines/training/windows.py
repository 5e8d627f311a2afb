"""Crop training of the detector: range x angle windows of the frames, the whole Doppler axis kept.

The detector is fully convolutional, so it learns from windows and runs on whole frames. A window costs what its
share of the grid costs: a 64 x 128 window of a 256 x 256 ``carrada`` frame is an eighth of the frame's
backbone, neck and head work (docs/guides/carrada-cpu.md measures the step). Windows start on multiples of the
output stride (4 bins), so a window's output cells are exactly the whole frame's cells there and its targets are
that window of the whole frame's (:func:`models.detector.targets.crop_centre_targets`); the network reads the
Cartesian channels of the window's own place on the grid (``window_origins``), so a position it learned in a
window is the position it sees on the whole frame.

:class:`WindowSampler` draws a window per frame: with probability ``object_share`` one that holds the centre of an
object picked at random (placed uniformly among the windows that hold it), otherwise one that holds no object
centre (uniformly among those: clutter only), falling back to any window where every window holds one.
:class:`WindowDataset` cuts each sample of a :class:`~pipelines.datasets.store.StoreDataset` (its earlier frames
the same way), reproducibly from ``(seed, epoch, frame)``. :func:`whole_frame_batch_norms` gives the trained
detector the BatchNorm statistics of whole frames, which it is validated and run on.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from models.detector.targets import OUTPUT_STRIDE
from pipelines.datasets.store import StoreDataset
from pipelines.evaluation.scoring import frame_centres


@dataclass(frozen=True)
class Window:
    """One drawn window: its first (range, angle) bins and whether an object centre lies inside it."""

    range_start: int
    angle_start: int
    holds_object: bool


@dataclass(frozen=True)
class WindowSampler:
    """Windows of ``size`` (range, angle) bins on a ``grid`` (R, A), both multiples of ``stride`` bins."""

    size: tuple[int, int]
    grid: tuple[int, int]
    object_share: float = 0.8
    stride: int = OUTPUT_STRIDE

    def __post_init__(self) -> None:
        for axis, (length, extent) in enumerate(zip(self.size, self.grid, strict=True)):
            name = ("range", "angle")[axis]
            if length < self.stride or length % self.stride or length > extent:
                raise ValueError(f"a window's {name} size must be a multiple of {self.stride} bins between "
                                 f"{self.stride} and the grid's {extent}, got {length}")
            if extent % self.stride:
                raise ValueError(f"the grid's {name} bins ({extent}) must be a multiple of {self.stride} for windows")
        if not 0.0 <= self.object_share <= 1.0:
            raise ValueError(f"object_share must be in [0, 1], got {self.object_share}")

    @property
    def cells(self) -> tuple[int, int]:
        """The window's size in output cells."""
        return self.size[0] // self.stride, self.size[1] // self.stride

    def draw(self, centres: np.ndarray, rng: np.random.Generator) -> Window:
        """A window for a frame whose objects' centres are ``centres`` (N, >= 2) (range, angle) bins."""
        height, width = self.grid[0] // self.stride, self.grid[1] // self.stride
        h, w = self.cells
        cells = (np.floor(np.asarray(centres, np.float64)[:, :2] / self.stride).astype(np.int64) if len(centres)
                 else np.zeros((0, 2), np.int64))
        if len(cells) and rng.random() < self.object_share:
            row, col = cells[rng.integers(len(cells))]
            r = rng.integers(max(0, row - h + 1), min(height - h, row) + 1)
            a = rng.integers(max(0, col - w + 1), min(width - w, col) + 1)
            return Window(int(r) * self.stride, int(a) * self.stride, True)
        rows, cols = np.arange(height - h + 1), np.arange(width - w + 1)
        holds = np.zeros((len(rows), len(cols)), bool)  # origins whose window holds a centre
        for row, col in cells:
            holds[max(0, row - h + 1):row + 1, max(0, col - w + 1):col + 1] = True
        free = np.argwhere(~holds)
        if len(free):
            r, a = free[rng.integers(len(free))]
            return Window(int(r) * self.stride, int(a) * self.stride, False)
        r, a = rng.integers(len(rows)), rng.integers(len(cols))
        return Window(int(r) * self.stride, int(a) * self.stride, True)


class WindowDataset(Dataset):
    """The samples of ``frames`` cut to windows: ``input`` (D, h, w) and ``history`` (H, D, h, w) cut alike (from
    frames read in either layout: read ``doppler_last``, only the window is transposed),
    ``window_origin`` int64 (2,) bins and ``window_holds_object`` added; the object table stays the whole
    frame's (targets are built whole, then cut). Call :meth:`set_epoch` before each epoch."""

    def __init__(self, frames: StoreDataset, sampler: WindowSampler, *, seed: int = 0) -> None:
        if tuple(sampler.grid) != (frames.profile.n_range, frames.profile.n_angle):
            raise ValueError(f"the sampler's grid {sampler.grid} is not the store's "
                             f"{(frames.profile.n_range, frames.profile.n_angle)}")
        self.frames = frames
        self.sampler = sampler
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, item: int) -> dict[str, Any]:
        sample = self.frames[item]
        rng = np.random.default_rng([self.seed, self.epoch, sample["frame"], 2])
        window = self.sampler.draw(frame_centres(sample), rng)
        r, a = window.range_start, window.angle_start
        h, w = self.sampler.size
        out = dict(sample)
        if self.frames.doppler_last:  # (R, A, D) as stored: only the window is transposed to (D, h, w)
            out["input"] = sample["input"][r:r + h, a:a + w].permute(2, 0, 1).contiguous()
        else:
            out["input"] = sample["input"][:, r:r + h, a:a + w].contiguous()
        if "history" in sample:
            out["history"] = sample["history"][..., r:r + h, a:a + w].contiguous()
        out["window_origin"] = torch.tensor([r, a], dtype=torch.int64)
        out["window_holds_object"] = window.holds_object
        return out


@torch.no_grad()
def whole_frame_batch_norms(model: torch.nn.Module, batches: Iterable[dict[str, torch.Tensor]]) -> int:
    """Set every BatchNorm's running statistics to those of whole frames; returns the frames seen.

    Trained on windows, mostly around objects, a detector's running statistics are the windows' (more object, less
    clutter than a whole frame): on whole frames they put its activations off scale (a ``carrada`` detector's
    validation loss went from 7 to 190 between two epochs; the same weights with whole-frame statistics scored 7.0).
    The weights are untouched: each BatchNorm's statistics are reset and averaged (cumulative, ``momentum`` None)
    over the ``batches`` (the model's keyword inputs: ``log_power`` normalised, whole frames) in training mode; the
    model's mode and momenta are restored. Training itself normalises with the batch's statistics, so this changes
    what evaluation sees and nothing of the training trajectory.
    """
    norms = [m for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    momenta = [m.momentum for m in norms]
    was_training = model.training
    for norm in norms:
        norm.reset_running_stats()
        norm.momentum = None
    model.train()
    seen = 0
    try:
        for batch in batches:
            model(**batch)
            seen += len(batch["log_power"])
    finally:
        for norm, momentum in zip(norms, momenta, strict=True):
            norm.momentum = momentum
        model.train(was_training)
    return seen
