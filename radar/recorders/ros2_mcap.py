"""Frames of predictions as ROS 2 messages in an MCAP file (``ros2msg`` encoding, CDR; the message definitions are
carried in the file), for ``ros2 bag play``::

    /radar/tracks   radar_msgs/msg/RadarTracks    one RadarTrack per object
    /radar/points   sensor_msgs/msg/PointCloud2   the labelled voxels (fields as the Foxglove recording's points)

Coordinates follow ROS (REP 103): x forward, y left, z up, so a point at radarseg's (x lateral to the right,
y forward) is published at (y, -x, 0). A RadarTrack's ``uuid`` holds b"radarseg" then the track id (big-endian
uint64; 0: the object has no track), its ``classification`` 32000 + the class id (radar_msgs leaves 0-2 to
NO_CLASSIFICATION, STATIC, DYNAMIC and permits vendor classes from 32000), its ``velocity`` the track's velocity
vector (else the radial velocity along the line of sight), its ``size`` the object's extent. Covariances are
not estimated (zeros).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import IO

import numpy as np
from mcap_ros2.writer import Writer

from radar.recorders.foxglove_mcap import recording_metadata, velocity_vector
from radar.recorders.frames import POINT_DTYPE, PredictionFrame, RecordingInfo, binary_output

UUID_PREFIX = b"radarseg"
VENDOR_CLASSIFICATION = 32000  # radar_msgs: vendor-specific classifications start here
TOPICS = {"tracks": "/radar/tracks", "points": "/radar/points"}

_HEADER = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
_VECTOR3 = """================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
"""
RADAR_TRACKS = """std_msgs/Header header
radar_msgs/RadarTrack[] tracks
""" + _HEADER + """================================================================================
MSG: radar_msgs/RadarTrack
unique_identifier_msgs/UUID uuid
geometry_msgs/Point position
geometry_msgs/Vector3 velocity
geometry_msgs/Vector3 acceleration
geometry_msgs/Vector3 size
uint16 NO_CLASSIFICATION=0
uint16 STATIC=1
uint16 DYNAMIC=2
uint16 classification
float32[6] position_covariance
float32[6] velocity_covariance
float32[6] acceleration_covariance
float32[6] size_covariance
================================================================================
MSG: unique_identifier_msgs/UUID
uint8[16] uuid
================================================================================
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
""" + _VECTOR3
POINT_CLOUD2 = """std_msgs/Header header
uint32 height
uint32 width
sensor_msgs/PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
""" + _HEADER + """================================================================================
MSG: sensor_msgs/PointField
uint8 INT8=1
uint8 UINT8=2
uint8 INT16=3
uint8 UINT16=4
uint8 INT32=5
uint8 UINT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
string name
uint32 offset
uint8 datatype
uint32 count
"""
_DATATYPE = {"f4": 7, "u1": 2, "u2": 4, "u4": 6}
POINT_FIELDS = [{"name": name, "offset": POINT_DTYPE.fields[name][1],
                 "datatype": _DATATYPE[POINT_DTYPE.fields[name][0].str[1:]], "count": 1} for name in POINT_DTYPE.names]


def track_uuid(track_id: int) -> list[int]:
    """The 16 bytes of a RadarTrack's uuid for ``track_id``."""
    return list(UUID_PREFIX + int(track_id).to_bytes(8, "big"))


def ros_points(points: np.ndarray) -> np.ndarray:
    """The points in ROS axes (x forward, y left)."""
    out = points.copy()
    out["x"], out["y"] = points["y"], -points["x"]
    return out


def _header(frame: PredictionFrame, info: RecordingInfo) -> dict:
    return {"stamp": {"sec": frame.time_ns // 1_000_000_000, "nanosec": frame.time_ns % 1_000_000_000},
            "frame_id": info.frame_id}


def radar_tracks(frame: PredictionFrame, info: RecordingInfo) -> dict:
    tracks = []
    for obj in frame.objects:
        vx, vy = velocity_vector(obj)
        tracks.append({
            "uuid": {"uuid": track_uuid(obj.track_id)},
            "position": {"x": obj.y, "y": -obj.x, "z": 0.0},
            "velocity": {"x": vy, "y": -vx, "z": 0.0},
            "acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
            "size": {"x": obj.size_y, "y": obj.size_x, "z": 1.0},
            "classification": VENDOR_CLASSIFICATION + obj.class_id,
            **{f"{name}_covariance": [0.0] * 6 for name in ("position", "velocity", "acceleration", "size")},
        })
    return {"header": _header(frame, info), "tracks": tracks}


def point_cloud2(frame: PredictionFrame, info: RecordingInfo) -> dict:
    data = ros_points(frame.points).tobytes()
    return {"header": _header(frame, info), "height": 1, "width": len(frame.points), "fields": POINT_FIELDS,
            "is_bigendian": False, "point_step": POINT_DTYPE.itemsize, "row_step": len(data), "data": data,
            "is_dense": True}


def write_ros2_mcap(frames: Iterable[PredictionFrame], info: RecordingInfo, out: str | Path | IO[bytes]) -> int:
    """Write the frames to ``out`` (a path or a binary file object); returns the number of frames."""
    with binary_output(out) as stream:
        writer = Writer(stream)
        tracks_schema = writer.register_msgdef("radar_msgs/msg/RadarTracks", RADAR_TRACKS)
        points_schema = writer.register_msgdef("sensor_msgs/msg/PointCloud2", POINT_CLOUD2)
        n = 0
        for frame in frames:
            writer.write_message(TOPICS["tracks"], tracks_schema, radar_tracks(frame, info), log_time=frame.time_ns,
                                 publish_time=frame.time_ns, sequence=frame.frame_index)
            writer.write_message(TOPICS["points"], points_schema, point_cloud2(frame, info), log_time=frame.time_ns,
                                 publish_time=frame.time_ns, sequence=frame.frame_index)
            n += 1
        writer.add_metadata("radarseg", recording_metadata(info))
        writer.finish()
    return n
