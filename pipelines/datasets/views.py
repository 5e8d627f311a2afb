"""The store read as the 2-D baselines see it: RD, RA and AD views, and windows of consecutive frames.

A sample is one *target* frame of a split with its RA and RD masks, and its views over a window of
``n_frames`` consecutive frames of the same sequence ending at the target (earlier frames only, oldest
first): TMVA-Net reads 5, SMVA-Net and U-Net 1. As in the reference (MVRSS drops the first
``n_frames - 1`` frames of every sequence), a target is usable only when all the frames
``frame_index - n_frames + 1 .. frame_index`` of its sequence are in the store and valid, so the first
``n_frames - 1`` frames of each sequence (and the frames after a quarantined one, within the window)
are neither trained on nor scored: :func:`scored_frames` says how many remain.

Views (dB, from the stored log power, :mod:`radar.transforms`): RD ``(R, D)`` log of the power summed
over angle / A, RA ``(R, A)`` max over Doppler, AD ``(A, D)`` max over range. They are scaled to about
[0, 1] by the minimum and maximum of each view over training frames (:class:`ViewStats`; MVRSS's
"tvt" normalisation, here from the train split only).
"""

from __future__ import annotations

import dataclasses
import os
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zarr
from torch import nn
from torch.utils.data import Dataset

from models.capabilities import Stage
from models.checkpoint import Checkpoint, load_checkpoint
from pipelines.datasets.spread import spread
from pipelines.datasets.store import frames_of_split, open_store
from radar import transforms
from radar.errors import UserError
from radar.input_kind import InputKind

VIEWS = ("rd", "ra", "ad")
MASK_VIEWS = ("rd", "ra")
STATS_FRAMES = 64  # training frames (evenly spread) whose views set the min/max scaling


def frame_views(log_power: np.ndarray) -> dict[str, np.ndarray]:
    """``{"rd": (R, D), "ra": (R, A), "ad": (A, D)}`` float32 views in dB of one log-power cube (R, A, D)."""
    log_power = np.asarray(log_power, np.float32)
    if log_power.ndim != 3:
        raise ValueError(f"expected a log-power cube (R, A, D), got shape {log_power.shape}")
    return {"rd": transforms.rd_view(log_power, kind=InputKind.log_power).astype(np.float32),
            "ra": transforms.ra_view(log_power, kind=InputKind.log_power),
            "ad": transforms.ad_view(log_power, kind=InputKind.log_power)}


def frame_windows(sequence_id: np.ndarray, frame_index: np.ndarray, targets: np.ndarray, available: np.ndarray,
                  n_frames: int) -> np.ndarray:
    """(K, n_frames) int64 store slots of the usable windows, oldest first, the target last.

    Args:
        sequence_id, frame_index: (N,) per store slot.
        targets: (M,) candidate target slots (e.g. the valid frames of a split), in order.
        available: (N,) bool, slots that may be read (valid frames).
        n_frames: window length >= 1.

    A window never crosses sequences and holds only frames before its target; targets whose window is
    incomplete are left out (K <= M).
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    slot_of = {(int(s), int(f)): slot for slot, (s, f, ok) in enumerate(zip(sequence_id, frame_index, available,
                                                                            strict=True)) if ok}
    windows = []
    for target in np.asarray(targets, np.int64):
        seq, index = int(sequence_id[target]), int(frame_index[target])
        slots = [slot_of.get((seq, index - back)) for back in range(n_frames - 1, -1, -1)]
        if all(slot is not None for slot in slots):
            windows.append(slots)
    return np.asarray(windows, np.int64).reshape(-1, n_frames)


def split_windows(path: str | Path, split: str | None, n_frames: int) -> np.ndarray:
    """:func:`frame_windows` of the valid frames of ``split`` of a store."""
    root = open_store(path)
    return frame_windows(root["sequence_id"][:], root["frame_index"][:], frames_of_split(root, split),
                         root["valid"][:].astype(bool), n_frames)


def scored_frames(path: str | Path, split: str | None, n_frames: int) -> int:
    """How many frames of ``split`` a model reading ``n_frames`` frames can be trained or scored on."""
    return len(split_windows(path, split, n_frames))


def view_class_counts(path: str | Path, split: str | None = "train") -> dict[str, np.ndarray]:
    """``{"rd": (C,), "ra": (C,)}`` int64 pixel counts per class of the RD and RA masks of ``split``."""
    root = open_store(path)
    slots = frames_of_split(root, split)
    num_classes = len(root.attrs["class_names"])
    counts = {}
    for view in MASK_VIEWS:
        masks = root[f"{view}_mask"]
        total = np.zeros(num_classes, np.int64)
        for start in range(0, len(slots), 64):  # whole shards at a time, a few MB each
            chunk = masks.get_orthogonal_selection((slots[start:start + 64],))
            total += np.bincount(chunk.ravel(), minlength=num_classes)[:num_classes]
        counts[view] = total
    return counts


@dataclass(frozen=True)
class ViewStats:
    """Min/max (dB) of each view over training frames; :meth:`normalise` maps them to 0 and 1."""

    rd_min: float
    rd_max: float
    ra_min: float
    ra_max: float
    ad_min: float
    ad_max: float

    def __post_init__(self) -> None:
        for view in VIEWS:
            low, high = getattr(self, f"{view}_min"), getattr(self, f"{view}_max")
            if not (np.isfinite(low) and np.isfinite(high) and high > low):
                raise ValueError(f"view {view!r}: need finite min < max, got {low}, {high}")

    def normalise(self, view: str, values: np.ndarray) -> np.ndarray:
        low, high = getattr(self, f"{view}_min"), getattr(self, f"{view}_max")
        return ((values - low) / (high - low)).astype(np.float32)

    def to_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ViewStats:
        names = {f.name for f in dataclasses.fields(cls)}
        missing = names - set(data)
        if missing:
            raise ValueError(f"view statistics lack {sorted(missing)}")
        return cls(**{name: float(data[name]) for name in names})

    @classmethod
    def from_store(cls, path: str | Path, split: str = "train", *, max_frames: int = STATS_FRAMES) -> ViewStats:
        """Statistics of up to ``max_frames`` frames of ``split`` spread evenly over it."""
        root = open_store(path)
        slots = frames_of_split(root, split)
        if not len(slots):
            raise UserError(f"store {path}: split {split!r} has no valid frames to take view statistics from")
        picked = slots[spread(len(slots), max_frames)]
        low = {view: np.inf for view in VIEWS}
        high = {view: -np.inf for view in VIEWS}
        for slot in picked:
            for view, values in frame_views(root["input"][int(slot)]).items():
                low[view] = min(low[view], float(values.min()))
                high[view] = max(high[view], float(values.max()))
        return cls(**{f"{view}_{end}": float(value[view]) for view in VIEWS
                      for end, value in (("min", low), ("max", high))})


def mirror_angle(values: np.ndarray, axis: int) -> np.ndarray:
    """Angle bin ``a -> (A - a) mod A`` along ``axis`` (left-right mirror, x -> -x, as the store's flips)."""
    return np.roll(np.flip(values, axis=axis), 1, axis=axis)


class ViewDataset(Dataset):
    """Windows of one split as baseline samples.

    Item: ``rd`` (T, R, D), ``ra`` (T, R, A), ``ad`` (T, A, D) float32 normalised views, T = ``n_frames``
    oldest first; ``rd_mask`` (R, D) and ``ra_mask`` (R, A) int64 of the target frame; ``frame`` (the
    target's store slot), ``sequence``, ``frame_index``, ``flipped``. ``targets`` (store slots) keeps only
    the windows ending at one of them, ``limit`` then an evenly spread subset. With ``flip_prob`` > 0 the whole
    window is mirrored in angle (RA, AD and the RA mask; RD is unchanged by construction), reproducibly
    from ``(seed, epoch, target slot)``: call :meth:`set_epoch` before each epoch.

    Views of the last few frames read are cached (consecutive windows share ``n_frames - 1`` frames).
    Arrays are opened lazily per process, so the dataset works in DataLoader workers.
    """

    def __init__(self, path: str | Path, split: str | None = "train", *, n_frames: int = 1,
                 stats: ViewStats | None = None, flip_prob: float = 0.0, seed: int = 0,
                 limit: int = 0, targets: np.ndarray | None = None, cache_frames: int = 16) -> None:
        if not 0.0 <= flip_prob <= 1.0:
            raise ValueError(f"flip_prob must be in [0, 1], got {flip_prob}")
        self.path = Path(path)
        self.split = split
        self.n_frames = n_frames
        self.windows = split_windows(path, split, n_frames)
        if targets is not None:  # only these target slots (models compared on the same frames)
            self.windows = self.windows[np.isin(self.windows[:, -1], np.asarray(targets, np.int64))]
        if limit and limit < len(self.windows):  # evenly spread subset (validation on a budget)
            self.windows = self.windows[spread(len(self.windows), limit)]
        self.stats = stats if stats is not None else ViewStats.from_store(path)
        self.flip_prob = flip_prob
        self.seed = seed
        self.epoch = 0
        self.cache_frames = cache_frames
        root = open_store(path)
        self._sequence_id = root["sequence_id"][:]
        self._frame_index = root["frame_index"][:]
        self._arrays: dict[str, zarr.Array] | None = None
        self._pid = -1
        self._cache: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.windows)

    def _open(self) -> dict[str, zarr.Array]:
        if self._arrays is None or self._pid != os.getpid():
            root = zarr.open_group(str(self.path), mode="r")
            self._arrays = {name: root[name] for name in ("input", "rd_mask", "ra_mask")}
            self._pid = os.getpid()
            self._cache.clear()
        return self._arrays

    def _views(self, slot: int) -> dict[str, np.ndarray]:
        if slot in self._cache:
            self._cache.move_to_end(slot)
            return self._cache[slot]
        views = {view: self.stats.normalise(view, values)
                 for view, values in frame_views(self._open()["input"][slot]).items()}
        self._cache[slot] = views
        while len(self._cache) > self.cache_frames:
            self._cache.popitem(last=False)
        return views

    def __getitem__(self, item: int) -> dict[str, Any]:
        if not 0 <= item < len(self.windows):
            raise IndexError(f"index {item} out of range for {len(self.windows)} windows")
        window = [int(slot) for slot in self.windows[item]]
        target = window[-1]
        arrays = self._open()
        frames = [self._views(slot) for slot in window]
        sample: dict[str, Any] = {view: np.stack([f[view] for f in frames]) for view in VIEWS}  # (T, H, W)
        sample["rd_mask"] = arrays["rd_mask"][target].astype(np.int64)
        sample["ra_mask"] = arrays["ra_mask"][target].astype(np.int64)
        rng = np.random.default_rng([self.seed, self.epoch, target])
        flipped = self.flip_prob > 0 and rng.random() < self.flip_prob
        if flipped:
            sample["ra"], sample["ad"] = mirror_angle(sample["ra"], 2), mirror_angle(sample["ad"], 1)
            sample["ra_mask"] = mirror_angle(sample["ra_mask"], 1)
        out = {name: torch.from_numpy(np.ascontiguousarray(value)) for name, value in sample.items()}
        out.update(frame=target, sequence=int(self._sequence_id[target]), frame_index=int(self._frame_index[target]),
                   flipped=bool(flipped))
        return out


def collate_views(samples: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Stack samples: views (B, T, H, W), masks (B, H, W); ``frame``/``sequence``/``frame_index`` lists."""
    batch: dict[str, Any] = {name: torch.stack([s[name] for s in samples]) for name in (*VIEWS, "rd_mask", "ra_mask")}
    for name in ("frame", "sequence", "frame_index", "flipped"):
        batch[name] = [s[name] for s in samples]
    return batch


def model_inputs(model: torch.nn.Module, batch: dict[str, Any], device: torch.device | str = "cpu") -> tuple:
    """Positional inputs of a baseline for a collated batch: ``(rd, ra, ad)`` for the multi-view
    networks, the one view ``(B, 1, H, W)`` for a U-Net (its ``view`` attribute)."""
    view = getattr(model, "view", None)
    if view is not None:
        return (batch[view][:, -1:].to(device),)
    return tuple(batch[name].to(device) for name in VIEWS)


def masks_of(batch: dict[str, Any], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """``{"rd": (B, R, D), "ra": (B, R, A)}`` int64 masks of a collated batch."""
    return {view: batch[f"{view}_mask"].to(device) for view in MASK_VIEWS}


def load_baseline(path: str | Path, *, device: str | torch.device = "cpu") -> tuple[nn.Module, Checkpoint, ViewStats]:
    """A trained baseline (eval mode), its checkpoint and the view scaling it was trained with."""
    checkpoint = load_checkpoint(path)
    if checkpoint.stage != Stage.BASELINE:
        raise UserError(f"{path}: not a baseline checkpoint ({checkpoint.describe()} given)")
    return checkpoint.build(device=device), checkpoint, ViewStats.from_dict(checkpoint.normalisation)
