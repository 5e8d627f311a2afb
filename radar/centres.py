"""Centres: a frame's scored object centres, the one output of every detector (the learned one, CFAR, the ground
truth). Region growing grows a region from each centre (its seed: the centre's voxel, moved to the brightest voxel
near it); the pipeline's final output is the segmented objects."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

# The centre defaults, one home for every caller (EraseNet, evaluation, segment, segment-batch, the service, the
# ONNX graphs' numpy decoding, the stores' object tables):
SCORE_THRESHOLD = 0.3
"""A decoded centre is kept when its heatmap score is at least this."""
MAX_OBJECTS = 32
"""Centres decoded per frame (top-k), and the rows of every per-frame object table."""


@dataclass(frozen=True)
class Centres:
    """N centres, sorted by descending score. Bins are fractional; Doppler in [0, D)."""

    score: np.ndarray  # (N,) float, higher is more confident
    range_bin: np.ndarray  # (N,)
    angle_bin: np.ndarray  # (N,)
    doppler_bin: np.ndarray  # (N,)

    def __post_init__(self) -> None:
        n = len(self.score)
        if not all(len(v) == n for v in (self.range_bin, self.angle_bin, self.doppler_bin)):
            raise ValueError("Centres fields must all have the same length")

    def __len__(self) -> int:
        return len(self.score)

    @property
    def bins(self) -> np.ndarray:
        """(N, 3) float64 (range, angle, Doppler) bins: where region growing starts."""
        return np.stack([self.range_bin, self.angle_bin, self.doppler_bin], axis=1).astype(np.float64).reshape(-1, 3)

    @classmethod
    def from_mapping(cls, data: Mapping) -> Centres:
        """From a dict of equal-length 1-D arrays or tensors (the detector's ``decode`` output)."""
        def arr(key):
            value = data[key]
            value = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
            return value.astype(np.float64).reshape(-1)

        return cls(arr("score"), arr("range_bin"), arr("angle_bin"), arr("doppler_bin"))

    @classmethod
    def from_bins(cls, bins: np.ndarray, score: np.ndarray | None = None) -> Centres:
        bins = np.asarray(bins, dtype=np.float64).reshape(-1, 3)
        score = np.ones(len(bins)) if score is None else np.asarray(score, dtype=np.float64)
        return cls(score, bins[:, 0], bins[:, 1], bins[:, 2])
