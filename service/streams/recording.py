"""A stream's recording: the frames this replica segmented for a stream, kept as the recorders' frames
(:mod:`radar.recorders.frames`: labelled voxels as points, objects with their track ids and velocity vectors, RA /
RD label maps) and written on request as MCAP (Foxglove's schemas), MCAP of ROS 2 messages or Rerun's ``.rrd``.

Like the earlier frames a stream's detector reads (:mod:`service.streams.history`), the recording is the replica's:
frames run by another replica (or before a restart) are not in it, and a frame's time is its ``seq`` frame periods
(a gap stays a gap). Streams are kept in least-recently-used order within ``max_bytes`` over every stream (a small
frame's record is tens of KB: its labelled voxels and two label maps); a stream beyond it loses its oldest frames
first. The cube's log power is not kept (NaN in the points, maps on black).
"""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from enum import StrEnum
from typing import Any

from radar.recorders.frames import PredictionFrame, RecordedObject, RecordingInfo, build_frame

Key = tuple[str, str]  # (tenant, stream id)
DEFAULT_MAX_BYTES = 256 * 2**20


class RecordingFormat(StrEnum):
    """A stream recording's format."""

    mcap = "mcap"  # MCAP with Foxglove's schemas
    ros2 = "ros2"  # MCAP of ROS 2 messages
    rrd = "rrd"  # Rerun

    @property
    def media_type(self) -> str:
        return "application/x-rerun-rrd" if self is RecordingFormat.rrd else "application/x-mcap"

    @property
    def suffix(self) -> str:
        return {"mcap": ".mcap", "ros2": ".ros2.mcap", "rrd": ".rrd"}[self.value]


def _size(frame: PredictionFrame) -> int:
    return frame.points.nbytes + frame.ra_labels.nbytes + frame.rd_labels.nbytes + 256 * (1 + len(frame.objects))


def stream_frame(net: Any, seq: int, stream_id: str, result: Any, tracks: list[Any]) -> PredictionFrame:
    """The recorded frame of a stream's frame ``seq``: the segmentation ``result`` and each object's track."""
    objects = tuple(RecordedObject(class_id=o.class_id, score=o.score, x=o.x, y=o.y, velocity_mps=o.velocity_mps,
                                   n_voxels=o.n_voxels, track_id=t.id, vx=float(t.mean[2]), vy=float(t.mean[3]))
                    for o, t in zip(result.objects, tracks, strict=True))
    return build_frame(net.profile, tick=seq, sequence=stream_id, frame_index=seq, labels=result.labels,
                       ra_labels=result.ra_mask, rd_labels=result.rd_mask, objects=objects)


class StreamRecordings:
    """Per stream, the recording info and frames this replica ran, within ``max_bytes`` over every stream."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._streams: OrderedDict[Key, tuple[RecordingInfo, list[PredictionFrame]]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def bytes(self) -> int:
        return self._bytes

    def keep(self, key: Key, info: RecordingInfo, frame: PredictionFrame) -> None:
        with self._lock:
            _, frames = self._streams.pop(key, (info, []))
            frames.append(frame)
            self._bytes += _size(frame)
            self._streams[key] = (info, frames)
            while self._bytes > self.max_bytes and self._streams:
                oldest_key, (oldest_info, oldest) = next(iter(self._streams.items()))
                self._bytes -= _size(oldest.pop(0))
                if not oldest:
                    del self._streams[oldest_key]

    def frames(self, key: Key) -> tuple[RecordingInfo, list[PredictionFrame]] | None:
        with self._lock:
            kept = self._streams.get(key)
            return None if kept is None else (kept[0], list(kept[1]))

    def forget(self, key: Key) -> None:
        with self._lock:
            _, frames = self._streams.pop(key, (None, []))
            self._bytes -= sum(_size(f) for f in frames)


def recording_bytes(info: RecordingInfo, frames: list[PredictionFrame], form: RecordingFormat) -> bytes:
    """The frames written in ``form`` (the writers load on first use: Rerun's SDK is not small)."""
    if form is RecordingFormat.rrd:
        from radar.recorders.rerun_rrd import rrd_bytes

        return rrd_bytes(frames, info)
    from radar.recorders.foxglove_mcap import write_foxglove_mcap
    from radar.recorders.ros2_mcap import write_ros2_mcap

    buffer = io.BytesIO()
    (write_foxglove_mcap if form is RecordingFormat.mcap else write_ros2_mcap)(frames, info, buffer)
    return buffer.getvalue()


def record_frame(recordings: StreamRecordings, key: Key, net: Any, seq: int, result: Any, tracks: list[Any]) -> None:
    """Keep stream frame ``seq`` (its segmentation ``result`` and each object's track) in the stream's recording."""
    info = RecordingInfo.for_profile(net.profile, tuple(net.class_names), {"stream": key[1]})
    recordings.keep(key, info, stream_frame(net, seq, key[1], result, tracks))
