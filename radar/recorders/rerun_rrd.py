"""Frames of predictions as a Rerun recording (``.rrd``), on the timelines ``frame`` (frame periods since the
recording's start) and ``time`` (that many frame periods, in seconds)::

    radar                       AnnotationContext: class id -> name and colour (background has none); static
    radar/points                Points3D (x, y, 0 m) with class ids, and the fields velocity, log_power, instance,
                                track_id beside them
    radar/objects               Boxes3D (centre, the voxels' x-y extent), class ids, label "class score #track", and
                                the fields score, track_id beside them
    radar/velocities            Arrows3D from each object's centre: its track's velocity vector (else the radial
                                velocity along the line of sight), m/s
    radar/ra_labels, rd_labels  SegmentationImage of the RA / RD label maps (range upwards), the annotation context's
                                colours; radar/ra_view, rd_view: the views in dB as images when the cube was at hand

Coordinates as radarseg's (x lateral to the right, y forward, metres).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import rerun as rr

from radar.recorders.foxglove_mcap import object_label, velocity_vector
from radar.recorders.frames import PredictionFrame, RecordingInfo
from radar.recorders.palette import class_rgb

APPLICATION_ID = "radarseg"


def annotation_context(info: RecordingInfo) -> rr.AnnotationContext:
    return rr.AnnotationContext([rr.AnnotationInfo(id=class_id, label=name, color=class_rgb(class_id))
                                 for class_id, name in enumerate(info.class_names)])


def _log_frame(rec: rr.RecordingStream, frame: PredictionFrame, info: RecordingInfo) -> None:
    rec.set_time("frame", sequence=frame.tick)
    rec.set_time("time", duration=frame.time_ns * 1e-9)
    points = frame.points
    positions = np.column_stack([points["x"], points["y"], points["z"]])
    # Rerun takes no empty batch of extra fields: a frame without points or objects logs the archetype alone
    point_fields = [rr.AnyValues(velocity=points["velocity"], log_power=points["log_power"],
                                 instance=points["instance"].astype(np.uint32),
                                 track_id=points["track_id"])] if len(points) else []
    rec.log("radar/points", rr.Points3D(positions, class_ids=points["class_id"], radii=0.15), *point_fields)
    objects = frame.objects
    centres = np.array([(o.x, o.y, 0.0) for o in objects], np.float32).reshape(-1, 3)
    half_sizes = np.array([(o.size_x / 2, o.size_y / 2, 0.5) for o in objects], np.float32).reshape(-1, 3)
    class_ids = np.array([o.class_id for o in objects], np.uint16)
    fields = [rr.AnyValues(score=np.array([o.score for o in objects], np.float32),
                           track_id=np.array([o.track_id for o in objects], np.uint32))] if objects else []
    rec.log("radar/objects", rr.Boxes3D(centers=centres, half_sizes=half_sizes, class_ids=class_ids,
                                        labels=[object_label(o, info) for o in objects]), *fields)
    vectors = np.array([(*velocity_vector(o), 0.0) for o in objects], np.float32).reshape(-1, 3)
    rec.log("radar/velocities", rr.Arrows3D(origins=centres, vectors=vectors, class_ids=class_ids))
    rec.log("radar/ra_labels", rr.SegmentationImage(frame.ra_labels[::-1]))
    rec.log("radar/rd_labels", rr.SegmentationImage(frame.rd_labels[::-1]))
    for name, view in (("ra_view", frame.ra_db), ("rd_view", frame.rd_db)):
        if view is not None:
            rec.log(f"radar/{name}", rr.Image(np.ascontiguousarray(view[::-1])))


def record(frames: Iterable[PredictionFrame], info: RecordingInfo, rec: rr.RecordingStream) -> int:
    """Log the frames to ``rec``; returns the number of frames."""
    rec.log("radar", annotation_context(info), static=True)
    rec.log("radar", rr.AnyValues(**{key: value for key, value in {
        "class_names": list(info.class_names), "preset": info.preset, "frame_period_s": info.frame_period_s,
        **info.metadata}.items()}), static=True)
    n = 0
    for frame in frames:
        _log_frame(rec, frame, info)
        n += 1
    return n


def _stream() -> rr.RecordingStream:
    """A recording stream on the frames' own timelines only (no wall-clock log time: the same frames write the same
    recording)."""
    rec = rr.RecordingStream(APPLICATION_ID, send_properties=False)
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    return rec


def write_rrd(frames: Iterable[PredictionFrame], info: RecordingInfo, out: str | Path) -> int:
    """Write the frames as an ``.rrd`` file at ``out``; returns the number of frames."""
    rec = _stream()
    rec.save(str(out))
    try:
        return record(frames, info, rec)
    finally:
        rec.flush()
        rec.disconnect()


def rrd_bytes(frames: Iterable[PredictionFrame], info: RecordingInfo) -> bytes:
    """The frames as the bytes of an ``.rrd`` file (a download)."""
    rec = _stream()
    stream = rec.binary_stream()
    record(frames, info, rec)
    rec.flush()
    data = stream.read(flush=True) or b""
    rec.disconnect()
    return data
