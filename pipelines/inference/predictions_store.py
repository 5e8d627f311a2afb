"""The predictions store written by batch segmentation (:mod:`pipelines.inference.segment_batch`): schema, encoding,
open.

Layout of ``PRED.zarr`` (zarr v3, sharded along the frame axis like the preprocessed store; see
:mod:`pipelines.datasets.sharded_store`)::

    labels       uint8   (N, R, A, D)  predicted class per RAD voxel (background outside the ROI)
    ra_mask      uint8   (N, R, A)     RA projection of ``labels``
    rd_mask      uint8   (N, R, D)     RD projection of ``labels``
    objects      float32 (N, K, 8)     NaN-padded object table, columns PREDICTION_OBJECT_FIELDS
    n_objects    int32   (N,)          rows of ``objects`` in use
    compute      float64 (N, 13)       MACs, seconds per stage, ROI voxels, ... (columns COMPUTE_FIELDS)
    source_slot  int32   (N,)          slot in the source store (recording: running frame number)
    sequence_id  int32   (N,)          index into the ``sequences`` attribute
    frame_index  int32   (N,)          frame index within its sequence
    valid        uint8   (N,)          1 segmented, 0 quarantined
    tracks       float32 (N, K, 3)     per object row: track id, vx, vy (m/s), NaN padded; written last, by
                                       pipelines.inference.batch_tracks (absent from stores made before it)
    progress/shard_NNNNN               one marker group per finished shard (attributes: its summary)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import zarr

from pipelines.datasets.sharded_store import Sharded, create_sharded_store, open_sharded_store
from radar.centres import MAX_OBJECTS
from radar.profiles import RadarProfile, resolve_profile

FORMAT = "radarseg.predictions"
VERSION = 1
PREDICTION_OBJECT_FIELDS = ("class_id", "score", "range_m", "angle_deg", "velocity_mps", "x", "y", "n_voxels")
COMPUTE_FIELDS = ("macs_detect", "macs_grow", "macs_segment", "macs_total",
                  "seconds_transform", "seconds_detect", "seconds_grow", "seconds_segment", "seconds_project",
                  "seconds_total", "roi_voxels", "visited_points", "detections")


@dataclass(frozen=True)
class PredictionLayout(Sharded):
    """Shapes, dtypes and shard boundaries of a predictions store of ``n_frames`` slots of one radar preset."""

    VOLUME_ARRAYS: ClassVar[tuple[str, ...]] = ("labels", "ra_mask", "rd_mask")
    preset: str
    n_frames: int
    shard_frames: int
    max_objects: int = MAX_OBJECTS
    radar_file: dict[str, Any] | None = field(default=None, compare=False)  # a radar described by a file

    @property
    def profile(self) -> RadarProfile:
        return resolve_profile(self.preset, self.radar_file, source="predictions store")

    def arrays(self) -> dict[str, tuple[tuple[int, ...], str, Any]]:
        """``name -> (per-frame shape, dtype, fill value)``."""
        R, A, D = self.profile.shape
        return {
            "labels": ((R, A, D), "uint8", 0),
            "ra_mask": ((R, A), "uint8", 0),
            "rd_mask": ((R, D), "uint8", 0),
            "objects": ((self.max_objects, len(PREDICTION_OBJECT_FIELDS)), "float32", float("nan")),
            "n_objects": ((), "int32", 0),
            "compute": ((len(COMPUTE_FIELDS),), "float64", float("nan")),
            "source_slot": ((), "int32", -1),
            "sequence_id": ((), "int32", -1),
            "frame_index": ((), "int32", -1),
            "valid": ((), "uint8", 0),
        }

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def encode_prediction(result: Any, layout: PredictionLayout) -> dict[str, np.ndarray]:
    """One frame's ``labels``, ``ra_mask``, ``rd_mask``, ``objects``, ``n_objects`` and ``compute`` from
    ERASE-Net's segmentation result; the object table keeps the first ``layout.max_objects`` objects."""
    table = np.full((layout.max_objects, len(PREDICTION_OBJECT_FIELDS)), np.nan, np.float32)
    for k, obj in enumerate(result.objects[: layout.max_objects]):
        table[k] = [getattr(obj, name) for name in PREDICTION_OBJECT_FIELDS]
    compute = result.compute
    values = {**{f"macs_{k}": v for k, v in compute.macs_by_stage().items()},
              **{f"seconds_{k}": v for k, v in compute.seconds_by_stage().items()},
              "roi_voxels": compute.roi_voxels, "visited_points": compute.visited_points,
              "detections": compute.detections}
    return {
        "labels": result.labels,
        "ra_mask": result.ra_mask,
        "rd_mask": result.rd_mask,
        "objects": table,
        "n_objects": np.int32(min(len(result.objects), layout.max_objects)),
        "compute": np.array([values[name] for name in COMPUTE_FIELDS], np.float64),
    }


def create_predictions(path: str | Path, layout: PredictionLayout, attributes: dict[str, Any]) -> zarr.Group:
    """Create an empty predictions store (``complete`` False until the job finishes it)."""
    return create_sharded_store(path, layout, attributes, store_format=FORMAT, version=VERSION)


def open_predictions(path: str | Path, *, require_complete: bool = True) -> zarr.Group:
    """Open a predictions store read-only; DataError when it is not one (or not finished)."""
    return open_sharded_store(path, store_format=FORMAT, version=VERSION, require_complete=require_complete,
                              what="predictions store", writer="job")
