"""``radarseg export recording PRED.zarr --mcap OUT.mcap --rrd OUT.rrd [--ros2 OUT.mcap]``: a predictions store as
recordings for Foxglove (MCAP, Foxglove's schemas), Rerun (``.rrd``) and ROS 2 (MCAP, ros2msg), each written in one
pass over the store (:mod:`pipelines.recordings.store_frames`, :mod:`radar.recorders`)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from pipelines.recordings.store_frames import open_store_recording, store_frames
from radar.errors import UserError
from radar.recorders.foxglove_mcap import write_foxglove_mcap
from radar.recorders.rerun_rrd import write_rrd
from radar.recorders.ros2_mcap import write_ros2_mcap

WRITERS = {"mcap": write_foxglove_mcap, "rrd": write_rrd, "ros2": write_ros2_mcap}


def check_outputs(outputs: dict[str, str | Path | None], *, overwrite: bool = False) -> dict[str, Path]:
    """The chosen outputs (at least one), each in an existing directory and not an existing file unless
    ``overwrite``; UserError naming the option otherwise."""
    chosen = {kind: Path(path) for kind, path in outputs.items() if path is not None}
    if not chosen:
        raise UserError("name at least one output: --mcap OUT.mcap, --rrd OUT.rrd or --ros2 OUT.mcap")
    if len(set(chosen.values())) < len(chosen):
        raise UserError(f"each output needs its own file, got {', '.join(f'--{k} {p}' for k, p in chosen.items())}")
    for kind, path in chosen.items():
        if not path.parent.is_dir():
            raise UserError(f"--{kind} {path}: the directory {path.parent} does not exist")
        if path.exists() and (path.is_dir() or not overwrite):
            raise UserError(f"--{kind} {path} exists (pass --overwrite to replace a file)")
    return chosen


def export_recording(predictions: str | Path, *, mcap: str | Path | None = None, rrd: str | Path | None = None,
                     ros2: str | Path | None = None, sequence: str | None = None, limit: int | None = None,
                     log_power: bool = True, overwrite: bool = False) -> dict[str, Any]:
    """Write the chosen recordings of the predictions store; returns, per output, its path, frames, bytes and
    seconds."""
    outputs = check_outputs({"mcap": mcap, "rrd": rrd, "ros2": ros2}, overwrite=overwrite)
    recording = open_store_recording(predictions, sequence=sequence, limit=limit)
    written: dict[str, Any] = {"predictions": str(predictions), "frames": len(recording), "outputs": {}}
    for kind, path in outputs.items():
        started = time.perf_counter()
        frames = WRITERS[kind](store_frames(recording, log_power=log_power), recording.info, path)
        written["outputs"][kind] = {"path": str(path), "frames": frames, "bytes": path.stat().st_size,
                                    "seconds": time.perf_counter() - started}
    return written
