"""What a recording of a predictions store must hold, read from the store with zarr and the radar profile alone."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipelines.inference.predictions_store import PREDICTION_OBJECT_FIELDS, PredictionLayout, open_predictions

COLUMN = {name: i for i, name in enumerate(PREDICTION_OBJECT_FIELDS)}


@dataclass
class ExpectedFrame:
    time_ns: int
    x: np.ndarray  # labelled voxels in (range, angle, Doppler) order
    y: np.ndarray
    velocity: np.ndarray
    class_id: np.ndarray
    objects: np.ndarray  # (K, 8)
    track_ids: np.ndarray  # (K,) int, 0 untracked
    ra_mask: np.ndarray
    rd_mask: np.ndarray


def expected_frames(path) -> tuple[list[ExpectedFrame], list[str]]:
    """The store's frames in recording order (sequence, then frame index; one period between sequences)."""
    root = open_predictions(path)
    profile = PredictionLayout(root.attrs["preset"], 1, 1, radar_file=root.attrs["radar_file"]).profile
    period_ns = profile.frame_period_s * 1e9
    frames, start = [], 0
    for s in range(len(root.attrs["sequences"])):
        slots = np.flatnonzero((root["sequence_id"][:] == s) & (root["valid"][:] == 1))
        slots = slots[np.argsort(root["frame_index"][slots])]
        for slot in slots:
            labels = root["labels"][slot]
            r, a, d = np.nonzero(labels)
            x, y = profile.xy(r, a)
            n = int(root["n_objects"][slot])
            tracks = np.nan_to_num(root["tracks"][slot, :n, 0]).astype(int)
            frames.append(ExpectedFrame(round((start + int(root["frame_index"][slot])) * period_ns), x, y,
                                        profile.velocity_mps(d), labels[r, a, d], root["objects"][slot, :n], tracks,
                                        root["ra_mask"][slot], root["rd_mask"][slot]))
        start += int(root["frame_index"][slots].max()) + 2
    return frames, list(root.attrs["class_names"])
