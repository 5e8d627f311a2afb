"""Frames of predictions as an MCAP file with Foxglove's well-known schemas (protobuf, from ``foxglove-sdk``).

Channels (each message stamped with its frame's time, ``frame_index`` frame periods apart)::

    /radar/points      foxglove.PointCloud   labelled voxels: x, y, z (m), velocity (m/s), log_power (dB),
                                             class_id, instance, track_id (POINT_DTYPE, packed)
    /radar/objects     foxglove.SceneUpdate  per object: a cube (its voxels' x-y extent), a velocity arrow (the
                                             track's vx, vy; else the radial velocity along the line of sight) and a
                                             text "class score #track"; metadata class_id, score, track_id
    /radar/ra_image    foxglove.RawImage     RA label map in class colours over the RA view (rgb8, range upwards)
    /radar/rd_image    foxglove.RawImage     RD label map likewise

The file also holds a metadata record ``radarseg`` (class names, preset, frame period). Foxglove opens it as it is;
any MCAP reader decodes it with the schemas it carries.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import IO

import foxglove.messages as fm
from mcap.writer import CompressionType, Writer

from radar.recorders.frames import POINT_DTYPE, PredictionFrame, RecordedObject, RecordingInfo, binary_output
from radar.recorders.palette import class_rgb, label_image

TOPICS = {"points": "/radar/points", "objects": "/radar/objects", "ra_image": "/radar/ra_image",
          "rd_image": "/radar/rd_image"}
_NUMERIC = {"f4": fm.PackedElementFieldNumericType.Float32, "u1": fm.PackedElementFieldNumericType.Uint8,
            "u2": fm.PackedElementFieldNumericType.Uint16, "u4": fm.PackedElementFieldNumericType.Uint32}
POINT_FIELDS = [fm.PackedElementField(name=name, offset=POINT_DTYPE.fields[name][1],
                                      type=_NUMERIC[POINT_DTYPE.fields[name][0].str[1:]])
                for name in POINT_DTYPE.names]
_SCHEMAS = {"points": fm.PointCloud, "objects": fm.SceneUpdate, "ra_image": fm.RawImage, "rd_image": fm.RawImage}


def _timestamp(time_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=time_ns // 1_000_000_000, nsec=time_ns % 1_000_000_000)


def point_cloud(frame: PredictionFrame, info: RecordingInfo) -> fm.PointCloud:
    return fm.PointCloud(timestamp=_timestamp(frame.time_ns), frame_id=info.frame_id,
                         pose=fm.Pose(position=fm.Vector3(x=0, y=0, z=0),
                                      orientation=fm.Quaternion(x=0, y=0, z=0, w=1)),
                         point_stride=POINT_DTYPE.itemsize, fields=POINT_FIELDS, data=frame.points.tobytes())


def velocity_vector(obj: RecordedObject) -> tuple[float, float]:
    """The object's velocity (m/s): its track's vector, else its radial velocity along the line of sight."""
    if math.isfinite(obj.vx) and math.isfinite(obj.vy):
        return obj.vx, obj.vy
    distance = math.hypot(obj.x, obj.y) or 1.0
    return obj.velocity_mps * obj.x / distance, obj.velocity_mps * obj.y / distance


def object_label(obj: RecordedObject, info: RecordingInfo) -> str:
    """The text shown beside an object: class, score and track id."""
    track = f" #{obj.track_id}" if obj.track_id else ""
    return f"{info.class_name(obj.class_id)} {obj.score:.2f}{track}"


def _entity(frame: PredictionFrame, row: int, obj: RecordedObject, info: RecordingInfo) -> fm.SceneEntity:
    r, g, b = class_rgb(obj.class_id)
    colour = fm.Color(r=r / 255, g=g / 255, b=b / 255, a=0.6)
    identity = fm.Quaternion(x=0, y=0, z=0, w=1)
    vx, vy = velocity_vector(obj)
    speed = math.hypot(vx, vy)
    # an arrow points along its pose's +x: rotate +x onto (vx, vy) about z
    half = 0.5 * math.atan2(vy, vx)
    arrow_pose = fm.Pose(position=fm.Vector3(x=obj.x, y=obj.y, z=0),
                         orientation=fm.Quaternion(x=0, y=0, z=math.sin(half), w=math.cos(half)))
    return fm.SceneEntity(
        timestamp=_timestamp(frame.time_ns), frame_id=info.frame_id,
        id=f"track-{obj.track_id}" if obj.track_id else f"object-{row}",
        lifetime=fm.Duration(sec=0, nsec=int(info.frame_period_s * 1e9)),
        metadata=[fm.KeyValuePair(key="class_id", value=str(obj.class_id)),
                  fm.KeyValuePair(key="class_name", value=info.class_name(obj.class_id)),
                  fm.KeyValuePair(key="score", value=repr(obj.score)),
                  fm.KeyValuePair(key="track_id", value=str(obj.track_id))],
        cubes=[fm.CubePrimitive(pose=fm.Pose(position=fm.Vector3(x=obj.x, y=obj.y, z=0), orientation=identity),
                                size=fm.Vector3(x=obj.size_x, y=obj.size_y, z=1.0), color=colour)],
        arrows=[fm.ArrowPrimitive(pose=arrow_pose, shaft_length=max(speed, 0.01), shaft_diameter=0.1,
                                  head_length=0.3, head_diameter=0.3, color=fm.Color(r=r / 255, g=g / 255, b=b / 255,
                                                                                      a=1.0))],
        texts=[fm.TextPrimitive(pose=fm.Pose(position=fm.Vector3(x=obj.x, y=obj.y, z=1.0), orientation=identity),
                                billboard=True, font_size=14, scale_invariant=True,
                                color=fm.Color(r=1, g=1, b=1, a=1), text=object_label(obj, info))])


def scene_update(frame: PredictionFrame, info: RecordingInfo) -> fm.SceneUpdate:
    return fm.SceneUpdate(deletions=[], entities=[_entity(frame, row, obj, info)
                                                  for row, obj in enumerate(frame.objects, start=1)])


def map_image(frame: PredictionFrame, info: RecordingInfo, which: str) -> fm.RawImage:
    """The RA (``which`` "ra") or RD ("rd") label map as an rgb8 image."""
    labels, db = (frame.ra_labels, frame.ra_db) if which == "ra" else (frame.rd_labels, frame.rd_db)
    image = label_image(labels, db, len(info.class_names))
    height, width = image.shape[:2]
    return fm.RawImage(timestamp=_timestamp(frame.time_ns), frame_id=f"{info.frame_id}_{which}", width=width,
                       height=height, encoding="rgb8", step=3 * width, data=image.tobytes())


def write_foxglove_mcap(frames: Iterable[PredictionFrame], info: RecordingInfo, out: str | Path | IO[bytes]) -> int:
    """Write the frames to ``out`` (a path or a binary file object); returns the number of frames."""
    with binary_output(out) as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="radarseg")
        channels = {}
        for key, message_type in _SCHEMAS.items():
            schema = message_type.get_schema()
            schema_id = writer.register_schema(name=schema.name, encoding=schema.encoding, data=schema.data)
            channels[key] = writer.register_channel(topic=TOPICS[key], message_encoding="protobuf",
                                                    schema_id=schema_id)
        n = 0
        for frame in frames:
            messages = {"points": point_cloud(frame, info), "objects": scene_update(frame, info),
                        "ra_image": map_image(frame, info, "ra"), "rd_image": map_image(frame, info, "rd")}
            for key, message in messages.items():
                writer.add_message(channels[key], log_time=frame.time_ns, publish_time=frame.time_ns,
                                   data=message.encode(), sequence=frame.frame_index)
            n += 1
        writer.add_metadata("radarseg", recording_metadata(info))
        writer.finish()
    return n


def recording_metadata(info: RecordingInfo) -> dict[str, str]:
    """The metadata record every MCAP recording carries (strings, as MCAP's metadata holds)."""
    return {"class_names": json.dumps(list(info.class_names)), "preset": info.preset,
            "frame_period_s": repr(info.frame_period_s), **info.metadata}
