"""A predictions store whose predictions are a simulated recording's ground truth (labels, masks, objects with score
1), tracked by segment-batch's own pass: a store shaped exactly like segment-batch's, with realistic voxels and
objects, in a second (no model runs). Used by the recording tests and benchmarks/recording_export.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.datasets.record import simulate_recording
from pipelines.datasets.sharded_store import finish_store, write_shard_arrays
from pipelines.inference.batch_tracks import write_tracks
from pipelines.inference.predictions_store import (
    COMPUTE_FIELDS,
    PREDICTION_OBJECT_FIELDS,
    PredictionLayout,
    create_predictions,
)
from radar.io.recording import Recording
from radar.profiles import describe_for_storage


def _row(obj, profile) -> list[float]:
    rng = float(np.hypot(obj.centre_x, obj.centre_y))
    values = {"class_id": obj.class_id, "score": 1.0, "range_m": rng,
              "angle_deg": float(np.degrees(np.arctan2(obj.centre_x, obj.centre_y))),
              "velocity_mps": float(profile.velocity_mps(obj.doppler_bin)), "x": obj.centre_x, "y": obj.centre_y,
              "n_voxels": obj.n_voxels}
    return [values[name] for name in PREDICTION_OBJECT_FIELDS]


def write_truth_predictions(out: str | Path, *, sequences: int, frames: int, seed: int = 7,
                            preset: str = "small") -> Path:
    """Simulate ``sequences`` x ``frames`` frames into ``out``/recording and write ``out``/pred.zarr from their truth;
    returns the store's path."""
    out = Path(out)
    recording = Recording(simulate_recording(preset=preset, sequences=sequences, frames=frames, seed=seed,
                                             out=out / "recording", progress=False))
    profile = recording.profile
    names = sorted(recording.sequences())
    refs = [(s, name, i) for s, name in enumerate(names) for i in range(recording.n_frames(name))]
    layout = PredictionLayout(profile.name, len(refs), len(refs), radar_file=describe_for_storage(profile))
    path = out / "pred.zarr"
    create_predictions(path, layout, {})
    buffers = {name: np.full((len(refs), *shape), fill, dtype)
               for name, (shape, dtype, fill) in layout.arrays().items()}
    for slot, (s, name, index) in enumerate(refs):
        frame = recording.read_frame(name, index)
        # an object the radar did not see (no labelled voxel) has no centre: it is no prediction
        objects = [obj for obj in frame.objects if obj.n_voxels > 0][: layout.max_objects]
        buffers["labels"][slot] = frame.labels
        buffers["ra_mask"][slot] = frame.labels.max(axis=2)
        buffers["rd_mask"][slot] = frame.labels.max(axis=1)
        buffers["objects"][slot, : len(objects)] = [_row(obj, profile) for obj in objects]
        buffers["n_objects"][slot] = len(objects)
        buffers["compute"][slot] = 0.0
        buffers["source_slot"][slot], buffers["sequence_id"][slot], buffers["frame_index"][slot] = slot, s, index
        buffers["valid"][slot] = 1
    write_shard_arrays(path, layout, 0, buffers)
    tracking = write_tracks(path, profile)
    finish_store(path, {"preset": profile.name, "radar_file": layout.radar_file,
                        "class_names": list(profile.all_class_names), "sequences": names,
                        "object_fields": list(PREDICTION_OBJECT_FIELDS), "compute_fields": list(COMPUTE_FIELDS),
                        "source": {"kind": "recording", "path": str(out / "recording"), "preset": profile.name},
                        "tracking": tracking})
    return path
