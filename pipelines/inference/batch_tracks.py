"""Tracks in a predictions store: after every shard of ``segment-batch`` is written, one sequential pass per
sequence (frames in ``frame_index`` order) runs the tracker (:mod:`radar.tracking`) over each frame's object
table and writes the array ``tracks`` (docs/design.md section 16)::

    tracks  float32 (N, K, 3)  per row of ``objects``: track id, vx, vy (m/s; x lateral, y forward), NaN padded

A frame that was quarantined or not segmented is a gap: the tracks coast over it (``Tracker.step(frames=k)``).
Track ids start at 1 in every sequence. The pass is cheap (well under a millisecond a frame) and idempotent: a
rerun writes the same array. A store written before tracking has no ``tracks``; readers check for it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from pipelines.inference.predictions_store import PREDICTION_OBJECT_FIELDS
from radar.profiles import RadarProfile
from radar.tracking import Measurements, Tracker, TrackerConfig, TrackStatus

TRACK_FIELDS = ("track_id", "vx", "vy")
_OBJ = {name: i for i, name in enumerate(PREDICTION_OBJECT_FIELDS)}


def _measurements(table: np.ndarray) -> Measurements:
    return Measurements(table[:, _OBJ["x"]].astype(np.float64), table[:, _OBJ["y"]].astype(np.float64),
                        table[:, _OBJ["velocity_mps"]].astype(np.float64), table[:, _OBJ["class_id"]].astype(np.int64),
                        table[:, _OBJ["score"]].astype(np.float64))


def track_sequence(objects: np.ndarray, n_objects: np.ndarray, frame_index: np.ndarray,
                   config: TrackerConfig) -> tuple[np.ndarray, dict[str, Any]]:
    """``tracks`` (F, K, 3) of one sequence's F frames (given in ``frame_index`` order) and its figures."""
    out = np.full((*objects.shape[:2], len(TRACK_FIELDS)), np.nan, np.float32)
    tracker = Tracker(config)
    confirmed: set[int] = set()
    previous, seconds = None, 0.0
    for k, (table, n, index) in enumerate(zip(objects, n_objects, frame_index, strict=True)):
        gap = 1 if previous is None else max(int(index) - previous, 1)
        previous = int(index)
        started = time.perf_counter()
        step = tracker.step(_measurements(table[: int(n)]), frames=gap)
        seconds += time.perf_counter() - started
        for row, track in enumerate(step.object_tracks):
            out[k, row] = (track.id, track.mean[2], track.mean[3])
            if track.status is TrackStatus.confirmed:
                confirmed.add(track.id)
    return out, {"tracks": tracker.next_id - 1, "confirmed": len(confirmed), "seconds": seconds}


def write_tracks(path: str | Path, profile: RadarProfile, config: TrackerConfig | None = None) -> dict[str, Any]:
    """Track every sequence of the (not yet complete) predictions store at ``path``; write ``tracks``; return the
    figures kept in the store's attributes (``tracking``)."""
    config = config or TrackerConfig.for_profile(profile)
    root = zarr.open_group(str(path), mode="r+")
    valid = root["valid"][:].astype(bool)
    sequence_id, frame_index = root["sequence_id"][:], root["frame_index"][:]
    objects, n_objects = root["objects"][:], root["n_objects"][:]
    tracks = np.full((*objects.shape[:2], len(TRACK_FIELDS)), np.nan, np.float32)
    totals = {"tracks": 0, "confirmed": 0, "seconds": 0.0}
    sequences = np.unique(sequence_id[valid])
    for s in sequences:
        slots = np.flatnonzero(valid & (sequence_id == s))
        slots = slots[np.argsort(frame_index[slots], kind="stable")]
        tracks[slots], figures = track_sequence(objects[slots], n_objects[slots], frame_index[slots], config)
        for key in totals:
            totals[key] += figures[key]
    chunks = root["objects"].chunks
    if "tracks" in root:
        del root["tracks"]
    root.create_array("tracks", data=tracks, chunks=(chunks[0], *tracks.shape[1:]), fill_value=float("nan"))
    frames = int(valid.sum())
    return {"fields": list(TRACK_FIELDS), "sequences": len(sequences), "tracks": totals["tracks"],
            "confirmed_tracks": totals["confirmed"], "frames": frames,
            "ms_per_frame": 1000 * totals["seconds"] / frames if frames else 0.0, "config": config.to_dict()}
