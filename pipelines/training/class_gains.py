"""A threshold per class for a detector with a heatmap per class, chosen on a store's validation split::

    radarseg train class-gains RUN/model.pt TUNED.pt --store STORE.zarr [--split val] [--frames N]

Each class's own heatmap channel is decoded alone (3x3 peaks, Doppler refined from the cube, as the product
decodes), its peaks matched one to one to that class's true objects (:func:`radar.metrics.match_frame`, 3 m and 3
Doppler bins, as the per-class recall of :class:`pipelines.evaluation.scoring.DetectionScorer`), and the threshold
with the best F1 over :data:`THRESHOLDS` is the class's. The detector keeps one operating threshold
(:data:`radar.centres.SCORE_THRESHOLD`): a class's gain is that threshold divided by its own
(:class:`models.detector.centernet.CentreNetHead` merges ``min(1, gain_c p_c)``), so the copy written needs no
other change anywhere the detector runs. Greedy matching in score order gives the peaks above any threshold the
same matches as at the lowest one, so one decoding per frame scores every threshold.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.capabilities import Stage
from models.checkpoint import load_checkpoint, save_checkpoint
from models.erasenet.detection import decode_centres, normalise_log_power
from pipelines.datasets.spread import subset
from pipelines.datasets.store import OBJECT_COLUMN, StoreDataset
from pipelines.datasets.store_info import StoreInfo
from radar.centres import MAX_OBJECTS, SCORE_THRESHOLD
from radar.errors import UserError
from radar.metrics import match_frame

THRESHOLDS = tuple(float(t) for t in np.round(np.arange(0.05, 0.601, 0.025), 3))
MATCH_DISTANCE = 3.0  # metres and Doppler bins


@dataclasses.dataclass(frozen=True)
class ClassCounts:
    """One class's matches over frames: at each threshold, peaks kept and peaks matched; its true objects."""

    name: str
    kept: np.ndarray  # (T,) peaks >= each threshold
    matched: np.ndarray  # (T,) of them matched to a true object of the class
    truths: int

    def table(self, frames: int) -> list[dict[str, float]]:
        rows = []
        for t, kept, matched in zip(THRESHOLDS, self.kept, self.matched, strict=True):
            precision = matched / kept if kept else 1.0
            recall = matched / self.truths if self.truths else 0.0
            f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
            rows.append({"threshold": t, "precision": float(precision), "recall": float(recall), "f1": float(f1),
                         "peaks_per_frame": float(kept / max(frames, 1))})
        return rows


def count_class_matches(detector: torch.nn.Module, normalisation: dict[str, float], store: StoreInfo, split: str, *,
                        max_frames: int = 0, batch_size: int = 8) -> tuple[list[ClassCounts], int]:
    """Per class, peaks kept and matched at every threshold of :data:`THRESHOLDS`, over the split's frames
    (the log power normalised with ``normalisation``, the detector's own, as the product does)."""
    classes = int(getattr(detector.head, "heatmap_classes", 1))
    names = store.class_names[1:]
    if classes != len(names):
        raise UserError(f"the detector has {classes} heatmap channel(s); a threshold per class needs one per class "
                        f"of the store ({len(names)}: {list(names)}): train it with --model-config "
                        f"'{{\"heatmap_classes\": {len(names)}}}'")
    dataset = StoreDataset(store.path, split, fields=("input", "objects"), normalise=False)
    indices = subset(len(dataset), max_frames)
    kept = np.zeros((classes, len(THRESHOLDS)), np.int64)
    matched = np.zeros_like(kept)
    truths = np.zeros(classes, np.int64)
    thresholds = np.asarray(THRESHOLDS)[:, None]
    detector.eval()
    for start in range(0, len(indices), batch_size):
        samples = [dataset[i] for i in indices[start:start + batch_size]]
        log_power = torch.stack([s["input"] for s in samples])  # (B, D, R, A) dB
        with torch.no_grad():
            outputs = detector(normalise_log_power(log_power, normalisation["mean"], normalisation["std"]))
        cubes = [frame.float().numpy().transpose(1, 2, 0) for frame in log_power]
        for c in range(classes):
            channel = {**outputs, "heatmap": outputs["class_heatmap"][:, c:c + 1]}
            frames = decode_centres(detector, channel, cubes, k=MAX_OBJECTS, score_threshold=THRESHOLDS[0])
            for sample, centres in zip(samples, frames, strict=True):
                table = sample["objects"][:int(sample["n_objects"])].double().numpy()
                table = table[table[:, OBJECT_COLUMN["class_id"]] == c + 1]
                truths[c] += len(table)
                xy = np.stack(store.profile.xy(centres.range_bin, centres.angle_bin), axis=1)
                tp = match_frame(xy, centres.doppler_bin, centres.score,
                                 table[:, [OBJECT_COLUMN["x"], OBJECT_COLUMN["y"]]],
                                 table[:, OBJECT_COLUMN["doppler_bin"]], MATCH_DISTANCE)
                above = centres.score[None, :] >= thresholds  # (T, N)
                kept[c] += above.sum(1)
                matched[c] += (above & tp[None, :]).sum(1)
    counts = [ClassCounts(names[c], kept[c], matched[c], int(truths[c])) for c in range(classes)]
    return counts, len(indices)


def choose_gains(counts: list[ClassCounts], frames: int) -> dict[str, Any]:
    """Each class's threshold (best F1; the higher threshold on a tie) and gain ``SCORE_THRESHOLD / threshold``."""
    chosen = {}
    for count in counts:
        table = count.table(frames)
        best = max(range(len(table)), key=lambda i: (round(table[i]["f1"], 6), table[i]["threshold"]))
        chosen[count.name] = {**table[best], "gain": SCORE_THRESHOLD / table[best]["threshold"], "table": table,
                              "truths": count.truths}
    return chosen


def write_class_gains(source: str | Path, target: str | Path, store: StoreInfo, *, split: str = "val",
                      max_frames: int = 0) -> dict[str, Any]:
    """Measure, choose and write a copy of the checkpoint ``source`` with the gains in its state dict
    (``extra["class_gains"]`` says how they were chosen). Returns that record."""
    checkpoint = load_checkpoint(source, stage=Stage.DETECTOR, option="SOURCE")
    detector = checkpoint.build()
    counts, frames = count_class_matches(detector, checkpoint.normalisation, store, split, max_frames=max_frames)
    chosen = choose_gains(counts, frames)
    gains = torch.tensor([chosen[c.name]["gain"] for c in counts])
    state = dict(checkpoint.state_dict)
    state["head.class_gain"] = gains.to(state["head.class_gain"].dtype)
    record = {"store": str(store.path), "split": split, "frames": frames, "operating_threshold": SCORE_THRESHOLD,
              "rule": "best F1 at 3 m / 3 Doppler bins", "classes": chosen}
    extra = {**checkpoint.extra, "class_gains": {k: v for k, v in record.items() if k != "classes"}
             | {"thresholds": {name: chosen[name]["threshold"] for name in chosen}}}
    save_checkpoint(dataclasses.replace(checkpoint, state_dict=state, extra=extra), target)
    return record
