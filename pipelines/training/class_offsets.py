"""An offset per class on a segmenter's logits, chosen on a store's frames from a detector's centres::

    radarseg train class-offsets SEGMENTER TUNED.pt --store STORE.zarr [--store ...] --detector DETECTOR [--split val]
        [--frames N]

The segmenter is trained with class-weighted cross entropy (weights ``1 / sqrt(frequency)``: a pedestrian voxel
counts about 13 background ones), which moves its decision boundary towards the rare classes: it labels more
pedestrian and cyclist voxels than there are, and one stray voxel on a line of sight makes its whole RA or RD cell
that class (the projection keeps any foreground voxel, docs/design.md section 8). An offset ``b_c`` added to class
``c``'s logit before the argmax moves the boundary back (docs/design.md section 7, "Class offsets"). It is chosen
where the product is scored: every frame of the split through the product's own path (the detector's centres at its
operating threshold, its earlier frames from the store if it reads them, region growing, the segmenter), the
objective being the mean of the RA and RD mIoU of whole frames as ``radarseg evaluate`` scores them.

Search: coordinate descent over the foreground classes (background stays 0) on a grid of :data:`STEP`, each class
moved to the best of :data:`MOVES` while the objective rises by more than :data:`MIN_GAIN`; each frame's logits are
computed once. The offsets are added to the classifier's bias (``W x + bias + b``), so the copy written runs
unchanged on every engine (eager, fused, ONNX float and int8); ``extra["class_offsets"]`` records them (``total``:
with any chosen before on the same checkpoint), the store, the frames and the objective before and after. Choose them
on frames nobody scores the product on.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.capabilities import Stage
from models.checkpoint import load_checkpoint, save_checkpoint
from models.runtime import load_erasenet
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.evaluation.evaluate import store_frames
from pipelines.evaluation.scoring import ViewConfusion
from pipelines.progress import progress
from radar import transforms
from radar.errors import UserError
from radar.region_growing import grow_regions

STEP = 0.125  # logit units
MOVES = tuple(STEP * k for k in range(-8, 9))  # a class's candidate changes in one pass, 0 included
MIN_GAIN = 1e-4  # of the objective (mIoU as a fraction)
MAX_PASSES = 4
CLASSIFIER_BIAS = "classifier.linear.bias"
ADVISED_FRAMES = 96  # fewer, and the offsets follow the few objects seen (the shipped ones: 384 frames)

log = logging.getLogger(__name__)


@dataclasses.dataclass
class FrameLogits:
    """One frame's ROI: voxels (N, 3), the segmenter's point logits (P, C) float32, each voxel's point, the masks."""

    voxels: np.ndarray
    logits: np.ndarray
    inverse: np.ndarray
    truth: dict[str, np.ndarray]


def frame_logits(net: Any, store: str | Path, split: str | None, *, max_frames: int = 0,
                 show_progress: bool = True) -> list[FrameLogits]:
    """Every frame of the split (``max_frames`` evenly spread, 0: all) through the product's path, logits kept."""
    root, slots = store_frames(store, net.profile, split, max_frames)
    inputs, ra_masks, rd_masks = root["input"], root["ra_mask"], root["rd_mask"]
    earlier = earlier_slots(root, net.history_frames) if net.history_frames else None
    frames = []
    for slot in progress(slots, desc="class offsets: logits", unit="frame", disable=not show_progress):
        slot = int(slot)
        log_power = inputs[slot].astype(np.float32)
        history = None if earlier is None else earlier_frames(inputs, earlier[slot])
        regions = grow_regions(log_power, net.detect(log_power, history=history), net.profile, net.region_config)
        truth = {"ra": ra_masks[slot], "rd": rd_masks[slot]}
        if len(regions) == 0:
            logits, inverse = np.zeros((0, net.profile.num_classes), np.float32), np.zeros(0, np.int64)
        else:
            points_logits, inverse, _, _ = net.point_logits(regions, log_power)
            logits = points_logits.float().cpu().numpy()
        frames.append(FrameLogits(regions.voxels, logits, inverse, truth))
    return frames


def score(frames: list[FrameLogits], offsets: np.ndarray, shape: tuple[int, int, int]) -> ViewConfusion:
    """The RA and RD confusion of whole frames with ``offsets`` (C,) added to the logits."""
    num_classes = len(offsets)
    confusion = ViewConfusion(num_classes)
    for frame in frames:
        classes = (frame.logits + offsets).argmax(axis=1).astype(np.uint8)[frame.inverse]
        confusion.add_masks(frame.truth, transforms.project_voxels(frame.voxels, classes, shape, 2, num_classes),
                            transforms.project_voxels(frame.voxels, classes, shape, 1, num_classes))
    return confusion


def objective(confusion: ViewConfusion) -> float:
    """The mean of RA and RD mIoU."""
    return (confusion.miou("ra") + confusion.miou("rd")) / 2


def choose_offsets(frames: list[FrameLogits], num_classes: int, shape: tuple[int, int, int]
                   ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """Coordinate descent from zero offsets; the offsets (C,) and each accepted move."""
    offsets = np.zeros(num_classes, np.float32)
    best = objective(score(frames, offsets, shape))
    moves = [{"offsets": offsets.tolist(), "objective": best}]
    for _ in range(MAX_PASSES):
        improved = False
        for c in range(1, num_classes):
            trials = {}
            for move in MOVES:
                if move == 0:
                    continue
                trial = offsets.copy()
                trial[c] += move
                trials[move] = objective(score(frames, trial, shape))
            move, value = max(trials.items(), key=lambda item: item[1])
            if value > best + MIN_GAIN:
                offsets[c] += move
                best = value
                improved = True
                moves.append({"offsets": offsets.tolist(), "objective": best})
        if not improved:
            break
    return offsets, moves


def write_class_offsets(source: str | Path, target: str | Path, *, detector: str | Path,
                        stores: list[str | Path], split: str | None = "val", max_frames: int = 0,
                        show_progress: bool = True) -> dict[str, Any]:
    """Measure, choose and write a copy of the segmenter checkpoint ``source`` with the offsets in its classifier's
    bias, on the split of every store (``max_frames`` of each). Returns the record also written to
    ``extra["class_offsets"]``."""
    checkpoint = load_checkpoint(source, stage=Stage.SEGMENTER, option="SOURCE")
    if CLASSIFIER_BIAS not in checkpoint.state_dict:
        raise UserError(f"{source}: a segmenter whose classifier has a bias ({CLASSIFIER_BIAS}) is needed")
    net = load_erasenet(load_checkpoint(detector, stage=Stage.DETECTOR, option="--detector"), checkpoint)
    frames = [frame for store in stores
              for frame in frame_logits(net, store, split, max_frames=max_frames, show_progress=show_progress)]
    if len(frames) < ADVISED_FRAMES:
        log.warning("class offsets chosen on %d frames: with fewer than %d they follow the few objects seen (on 4 "
                    "frames of a 48-sequence store the pedestrian offset came out +1.1, on 384 frames -1.0)",
                    len(frames), ADVISED_FRAMES)
    offsets, moves = choose_offsets(frames, net.profile.num_classes, net.profile.shape)
    before, after = score(frames, np.zeros_like(offsets), net.profile.shape), score(frames, offsets, net.profile.shape)
    state = dict(checkpoint.state_dict)
    bias = state[CLASSIFIER_BIAS]
    state[CLASSIFIER_BIAS] = (bias.float() + torch.from_numpy(offsets)).to(bias.dtype)
    earlier = checkpoint.extra.get("class_offsets", {}).get("total", {})
    record = {
        "offsets": dict(zip(checkpoint.class_names, offsets.tolist(), strict=True)),
        "total": {name: earlier.get(name, 0.0) + float(o) for name, o in zip(checkpoint.class_names, offsets,
                                                                              strict=True)},
        "stores": [str(store) for store in stores], "split": split, "frames": len(frames), "detector": str(detector),
        "objective": "mean of RA and RD mIoU of whole frames, the detector's centres",
        "before": _figures(before, checkpoint.class_names), "after": _figures(after, checkpoint.class_names),
        "moves": moves,
    }
    save_checkpoint(dataclasses.replace(checkpoint, state_dict=state,
                                        extra={**checkpoint.extra, "class_offsets": record}), target)
    return record


def _figures(confusion: ViewConfusion, class_names: tuple[str, ...]) -> dict[str, Any]:
    summary = confusion.summary(class_names)
    return {view.upper(): {"mIoU": s["mIoU"], "iou": s["iou"]} for view, s in summary.items()}
