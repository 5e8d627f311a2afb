"""Calibration frames for the int8 export, from the train split of a preprocessed store.

The int8 graphs (:mod:`models.export.quantize`) are calibrated on log-power frames; a store's train split gives
frames of the radar the model serves. ``models`` never reads a store, so this wing does and hands the cubes in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.export.export_cache import Int8Calibration
from models.export.quantize import CALIBRATION_FRAMES, METHODS
from pipelines.datasets.store import frames_of_split, open_store
from radar.profiles import RadarProfile


def store_calibration(store: str | Path, profile: RadarProfile, *, frames: int = CALIBRATION_FRAMES,
                      methods: tuple[str, ...] = METHODS) -> Int8Calibration:
    """``frames`` log-power cubes (R, A, D) float32 dB spread evenly over the store's train split.

    Raises:
        ValueError: ``frames`` < 1, a store of another preset than ``profile``, or one without train frames.
    """
    if frames < 1:
        raise ValueError(f"calibration frames must be >= 1, got {frames}")
    root = open_store(store)
    if root.attrs["preset"] != profile.name:
        raise ValueError(f"calibration store {store} is preset {root.attrs['preset']!r}, the model {profile.name!r}")
    slots = frames_of_split(root, "train")
    if len(slots) == 0:
        raise ValueError(f"store {store} has no train frames to calibrate on")
    chosen = slots[np.unique(np.linspace(0, len(slots) - 1, min(frames, len(slots))).round().astype(int))]
    cubes = tuple(np.asarray(root["input"][int(slot)], dtype=np.float32) for slot in chosen)
    description = {"source": "store", "store": str(store), "split": "train",
                   "preset": profile.name, "frames": [int(s) for s in chosen]}
    return Int8Calibration(cubes, description, tuple(methods))
