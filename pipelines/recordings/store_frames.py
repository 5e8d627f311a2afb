"""A predictions store (``segment-batch``'s output, :mod:`pipelines.inference.predictions_store`) read as the frames
the recorders write (:mod:`radar.recorders.frames`).

Frames come in recording order: sequences in the store's order, each sequence's frames by ``frame_index``;
quarantined slots are left out. A frame's time is ``frame_index`` frame periods after its sequence's start, and each
sequence starts one frame period after the previous one's last frame, so that one file holds them all on one
timeline. Objects carry their track (the store's ``tracks``; untracked without it). The points' log power and the
maps' dB views come from the store's source (its ``source`` attribute: the preprocessed store or the recording it
was segmented from) when it can still be read; otherwise they are left out (NaN log power, label maps on black).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from pipelines.inference.predictions_store import PREDICTION_OBJECT_FIELDS, PredictionLayout, open_predictions
from radar import transforms
from radar.errors import DataError, UserError
from radar.profiles import RadarProfile
from radar.recorders.frames import PredictionFrame, RecordedObject, RecordingInfo, build_frame

log = logging.getLogger(__name__)

_COLUMN = {name: i for i, name in enumerate(PREDICTION_OBJECT_FIELDS)}
LogPowerReader = Callable[[int, str, int], "np.ndarray | None"]  # (slot, sequence, frame_index) -> (R, A, D) dB


@dataclass(frozen=True)
class StoreRecording:
    """What a predictions store records: its radar, the recording's shared facts and the slots to record, in order,
    with each slot's tick (frame periods since the start)."""

    root: zarr.Group
    profile: RadarProfile
    info: RecordingInfo
    slots: tuple[int, ...]
    ticks: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.slots)


def open_store_recording(path: str | Path, *, sequence: str | None = None, limit: int | None = None) -> StoreRecording:
    """The recording of the predictions store at ``path`` (DataError when it is not a finished one); ``sequence``:
    that sequence only; ``limit``: its first ``limit`` frames."""
    if limit is not None and limit < 1:
        raise UserError(f"--limit must be >= 1, got {limit}")
    root = open_predictions(path)
    attrs = root.attrs
    layout = PredictionLayout(attrs["preset"], root["valid"].shape[0], 1, radar_file=attrs.get("radar_file"))
    profile = layout.profile
    sequences = list(attrs["sequences"])
    if sequence is not None and sequence not in sequences:
        raise UserError(f"--sequence {sequence!r}: the store holds sequences {sequences}")
    valid = root["valid"][:].astype(bool)
    sequence_id, frame_index = root["sequence_id"][:], root["frame_index"][:]
    slots, ticks, start = [], [], 0
    for s, name in enumerate(sequences):
        if sequence is not None and name != sequence:
            continue
        mine = np.flatnonzero(valid & (sequence_id == s))
        mine = mine[np.argsort(frame_index[mine], kind="stable")]
        slots += mine.tolist()
        ticks += (start + frame_index[mine]).tolist()
        start += int(frame_index[mine].max()) + 2 if len(mine) else 0
    if not slots:
        raise DataError(path, "no segmented frame to record" + (f" in sequence {sequence!r}" if sequence else ""))
    metadata = {"store": str(Path(path).absolute()), "sequences": ",".join(sequences)}
    info = RecordingInfo.for_profile(profile, tuple(attrs["class_names"]), metadata)
    return StoreRecording(root, profile, info, tuple(slots[:limit]), tuple(ticks[:limit]))


def source_log_power(root: zarr.Group) -> LogPowerReader | None:
    """A reader of each slot's log power from the store's source, or None when the source cannot be read."""
    source = root.attrs.get("source") or {}
    path = source.get("path")
    try:
        if source.get("kind") == "store":
            from pipelines.datasets.store import open_store

            inputs = open_store(path)["input"]
            slot_of = root["source_slot"][:]
            return lambda slot, sequence, index: inputs[int(slot_of[slot])].astype(np.float32)
        if source.get("kind") == "recording":
            from radar.io.recording import Recording

            recording = Recording(path)
            return lambda slot, sequence, index: transforms.log_power(recording.read_frame(sequence, index).cube)
    except (DataError, OSError, KeyError, TypeError) as exc:
        log.warning("the predictions' source %s cannot be read (%s): recorded without log power", path, exc)
        return None
    log.warning("the predictions store names no readable source: recorded without log power")
    return None


def _objects(table: np.ndarray, n: int, tracks: np.ndarray | None) -> tuple[RecordedObject, ...]:
    out = []
    for k in range(n):
        row = table[k]
        track = (0, float("nan"), float("nan")) if tracks is None or np.isnan(tracks[k, 0]) else tracks[k]
        out.append(RecordedObject(class_id=int(row[_COLUMN["class_id"]]), score=float(row[_COLUMN["score"]]),
                                x=float(row[_COLUMN["x"]]), y=float(row[_COLUMN["y"]]),
                                velocity_mps=float(row[_COLUMN["velocity_mps"]]),
                                n_voxels=int(row[_COLUMN["n_voxels"]]), track_id=int(track[0]),
                                vx=float(track[1]), vy=float(track[2])))
    return tuple(out)


def store_frames(recording: StoreRecording, *, log_power: bool = True) -> Iterator[PredictionFrame]:
    """The recording's frames, one slot read at a time; ``log_power``: read the source's cubes when it can be."""
    root = recording.root
    read_log_power = source_log_power(root) if log_power else None
    sequences = list(root.attrs["sequences"])
    tracks = root["tracks"] if "tracks" in root else None
    objects, n_objects = root["objects"][:], root["n_objects"][:]
    sequence_id, frame_index = root["sequence_id"][:], root["frame_index"][:]
    labels, ra_mask, rd_mask = root["labels"], root["ra_mask"], root["rd_mask"]  # looked up once (not per frame)
    for slot, tick in zip(recording.slots, recording.ticks, strict=True):
        sequence, index = sequences[int(sequence_id[slot])], int(frame_index[slot])
        cube_db = None
        if read_log_power is not None:
            try:
                cube_db = read_log_power(slot, sequence, index)
            except DataError as exc:
                log.warning("frame %s/%d: source frame unreadable (%s): recorded without log power", sequence, index,
                            exc)
        yield build_frame(recording.profile, tick=tick, sequence=sequence, frame_index=index,
                          labels=labels[slot], ra_labels=ra_mask[slot], rd_labels=rd_mask[slot],
                          objects=_objects(objects[slot], int(n_objects[slot]),
                                           None if tracks is None else tracks[slot]),
                          log_power=cube_db)
