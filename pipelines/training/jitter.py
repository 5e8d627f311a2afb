"""Seed jitter for the segmenter stage: errors added to ground-truth centres so that training ROIs are
grown from seeds as wrong as the detector's (measured on a split), or from Gaussian errors when no
detector is given."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.checkpoint import load_checkpoint
from models.erasenet.detection import detect_centres
from pipelines.datasets.spread import subset
from pipelines.datasets.store import StoreDataset
from pipelines.evaluation.scoring import frame_centres
from pipelines.training.config import DEFAULT_JITTER_STD
from radar.centres import SCORE_THRESHOLD
from radar.doppler import DOPPLER_REFINEMENT, DopplerRefinement
from radar.errors import UserError

JITTER_MATCH_M = 3.0  # a detection within this many metres (and bins of Doppler) of a truth is "its" detection


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


def _match(pred: np.ndarray, truth: np.ndarray, profile) -> tuple[list[np.ndarray], int, int]:  # noqa: ANN001
    """Residuals of the truths matched to their nearest unused detection, misses, unmatched detections."""
    pred_xy = np.stack(profile.xy(pred[:, 0], pred[:, 1]), axis=1)
    truth_xy = np.stack(profile.xy(truth[:, 0], truth[:, 1]), axis=1)
    used = np.zeros(len(pred), bool)
    residuals, misses = [], 0
    for t in range(len(truth)):
        dist = np.linalg.norm(pred_xy - truth_xy[t], axis=1)
        ok = (dist <= JITTER_MATCH_M) & (np.abs(pred[:, 2] - truth[t, 2]) < JITTER_MATCH_M) & ~used
        if ok.any():
            j = np.flatnonzero(ok)[np.argmin(dist[ok])]
            used[j] = True
            residuals.append(pred[j] - truth[t])
        else:
            misses += 1
    return residuals, misses, int((~used).sum())


@torch.no_grad()
def measure_detector_errors(detector_path: str | Path, store: str | Path, split: str = "val", *,
                            score_threshold: float = SCORE_THRESHOLD, max_frames: int = 0,
                            device: torch.device | str = "cpu",
                            doppler_refinement: DopplerRefinement | None = DOPPLER_REFINEMENT) -> SeedJitter:
    """Errors of a trained detector on a split: for each ground-truth object, the nearest detection
    within :data:`JITTER_MATCH_M` metres and Doppler bins gives a residual (prediction - truth, bins).
    Also reports the miss rate and false positives per frame (in ``stats``). Doppler is refined from the cube as
    EraseNet refines it (:mod:`radar.doppler`) unless ``doppler_refinement`` is None."""
    checkpoint = load_checkpoint(detector_path)
    detector = checkpoint.build(device=device)
    profile = checkpoint.profile
    dataset = StoreDataset(store, split, fields=("input", "objects"), normalise=False)
    mean_db, std_db = checkpoint.normalisation["mean"], checkpoint.normalisation["std"]
    residuals, misses, truths, false_pos = [], 0, 0, 0
    indices = subset(len(dataset), max_frames)
    for start in range(0, len(indices), 8):
        samples = [dataset[i] for i in indices[start:start + 8]]
        log_power = torch.stack([s["input"] for s in samples])  # (B, D, R, A) dB
        # the centres EraseNet grows regions from, Doppler refined as it refines them
        frames = detect_centres(detector, log_power, mean_db=mean_db, std_db=std_db, score_threshold=score_threshold,
                                doppler_refinement=doppler_refinement, device=device)[1]
        for sample, centres in zip(samples, frames, strict=True):
            truth = frame_centres(sample)
            found, missed, unmatched = _match(centres.bins, truth, profile)
            residuals += found
            misses += missed
            false_pos += unmatched
            truths += len(truth)
    residuals_arr = np.asarray(residuals, np.float64).reshape(-1, 3)
    if not len(indices):
        raise UserError(
            f"--jitter-from {detector_path}: split {split!r} of {store} has no frames to measure the detector's "
            f"errors on; give Gaussian seed errors instead with --jitter-std R A D (bins, e.g. --jitter-std "
            f"{' '.join(f'{v:g}' for v in DEFAULT_JITTER_STD)}), or preprocess with a non-zero validation fraction")
    if not len(residuals_arr):
        raise UserError(
            f"--jitter-from {detector_path}: the detector matched none of the {truths} objects in {len(indices)} "
            f"frames of split {split!r} of {store} (a match is a detection scoring >= {score_threshold} within "
            f"{JITTER_MATCH_M:g} m and {JITTER_MATCH_M:g} Doppler bins of a true centre), so its errors cannot be "
            f"measured; train the detector longer, or give Gaussian seed errors instead with --jitter-std R A D "
            f"(bins, e.g. --jitter-std {' '.join(f'{v:g}' for v in DEFAULT_JITTER_STD)})")
    stats = {"split": split, "frames": len(indices), "objects": truths, "matched": len(residuals_arr),
             "miss_rate": misses / max(truths, 1), "false_positives_per_frame": false_pos / max(len(indices), 1),
             "score_threshold": score_threshold, "match_m": JITTER_MATCH_M,
             "mean_bins": residuals_arr.mean(axis=0).tolist(),
             "abs_p90_bins": np.percentile(np.abs(residuals_arr), 90, axis=0).tolist()}
    std = tuple(float(v) for v in residuals_arr.std(axis=0))
    return SeedJitter(residuals_arr, std, f"measured: {detector_path}", stats)
