"""One frame of predictions as every recorder writes it: the labelled voxels as points in metres, the objects with
their tracks, and the RA / RD label maps, timestamped by the radar's frame period.

The recorders (Foxglove MCAP, ROS 2 MCAP, Rerun) take these frames and nothing else, so that a predictions store
(``pipelines.recordings``) and a service stream write the same recording from the same numbers.

Points: every voxel with a class (label > 0), at its range and angle bin's centre (``RadarProfile.xy``: x lateral,
y forward, z 0; metres), with the radial velocity of its Doppler bin (m/s), its log power (dB; NaN when the cube is
not at hand), its class, its instance (the row + 1 of the nearest object of its class in x-y, 0 when its class has
no object) and that object's track id (0 when none).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from radar.profiles import RadarProfile

POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("velocity", "<f4"), ("log_power", "<f4"),
                        ("class_id", "u1"), ("instance", "<u2"), ("track_id", "<u4")])
"""The points' fields, packed little-endian as written (Foxglove PointCloud and ROS 2 PointCloud2 alike)."""
MIN_BOX_M = 0.5  # an object's box is at least this wide: a single-voxel object stays visible


@dataclass(frozen=True)
class RecordedObject:
    """One object of a frame: its class, detector score, centre (m), radial velocity (m/s, positive receding), its
    track (id 0: none; velocity vector vx, vy in m/s, NaN when untracked) and its voxels' extent in x and y (m)."""

    class_id: int
    score: float
    x: float
    y: float
    velocity_mps: float
    n_voxels: int
    track_id: int = 0
    vx: float = float("nan")
    vy: float = float("nan")
    size_x: float = MIN_BOX_M
    size_y: float = MIN_BOX_M


@dataclass(frozen=True)
class PredictionFrame:
    """A frame as recorded: ``points`` (N,) of POINT_DTYPE, ``objects``, the RA (R, A) and RD (R, D) label maps
    (uint8 class ids) and, when the cube is at hand, the RA / RD views in dB (float32, same shapes). ``tick``: frame
    periods since the recording's start (its ``time_ns``: ``tick`` frame periods)."""

    tick: int
    time_ns: int
    sequence: str
    frame_index: int
    points: np.ndarray
    objects: tuple[RecordedObject, ...]
    ra_labels: np.ndarray
    rd_labels: np.ndarray
    ra_db: np.ndarray | None = None
    rd_db: np.ndarray | None = None


@dataclass(frozen=True)
class RecordingInfo:
    """What a whole recording shares: the class names (index = class id, 0 background), the radar's preset, its
    frame period, its axes' extents (for the maps) and the coordinate frame's name."""

    class_names: tuple[str, ...]
    preset: str
    frame_period_s: float
    max_range_m: float
    max_velocity_mps: float
    frame_id: str = "radar"
    metadata: dict[str, str] = field(default_factory=dict)

    @classmethod
    def for_profile(cls, profile: RadarProfile, class_names: tuple[str, ...] | None = None,
                    metadata: dict[str, str] | None = None) -> RecordingInfo:
        """``class_names``: every class's name by class id, background (0) first, as a model's checkpoint names them
        (default: the profile's)."""
        names = tuple(class_names) if class_names is not None else profile.all_class_names
        return cls(names, profile.name, profile.frame_period_s, profile.max_range, profile.max_velocity,
                   metadata=dict(metadata or {}))

    def class_name(self, class_id: int) -> str:
        return self.class_names[class_id] if 0 <= class_id < len(self.class_names) else f"class {class_id}"


def labelled_points(labels: np.ndarray, profile: RadarProfile, objects: tuple[RecordedObject, ...],
                    log_power: np.ndarray | None = None) -> np.ndarray:
    """The points (N,) of POINT_DTYPE of every labelled voxel of ``labels`` (R, A, D), in (range, angle, Doppler)
    bin order; ``log_power`` (R, A, D) dB gives their log power (NaN without it)."""
    r, a, d = np.nonzero(labels)
    points = np.zeros(len(r), POINT_DTYPE)
    x_ra, y_ra = profile.ra_cartesian
    points["x"], points["y"] = x_ra[r, a], y_ra[r, a]
    points["velocity"] = profile.velocity_mps(d)
    points["log_power"] = np.nan if log_power is None else log_power[r, a, d]
    points["class_id"] = labels[r, a, d]
    instance = _nearest_object(points, objects)
    points["instance"] = instance
    track_of_row = np.array([0, *(obj.track_id for obj in objects)], np.uint32)
    points["track_id"] = track_of_row[instance]
    return points


def _nearest_object(points: np.ndarray, objects: tuple[RecordedObject, ...]) -> np.ndarray:
    """Per point, the row + 1 of the nearest object of its class in x-y (0 when its class has none)."""
    if not objects or not len(points):
        return np.zeros(len(points), np.uint16)
    centres = np.array([(o.x, o.y) for o in objects], np.float32)  # (K, 2)
    classes = np.array([o.class_id for o in objects])
    dist = (points["x"][:, None] - centres[None, :, 0]) ** 2 + (points["y"][:, None] - centres[None, :, 1]) ** 2
    dist[points["class_id"][:, None] != classes[None, :]] = np.inf  # (N, K)
    nearest = np.argmin(dist, axis=1)
    found = np.isfinite(dist[np.arange(len(points)), nearest])
    return np.where(found, nearest + 1, 0).astype(np.uint16)


def with_extents(objects: tuple[RecordedObject, ...], points: np.ndarray) -> tuple[RecordedObject, ...]:
    """The objects with their box sized by their points' x and y extent (at least MIN_BOX_M)."""
    sized = []
    for row, obj in enumerate(objects, start=1):
        mine = points[points["instance"] == row]
        if len(mine):
            size_x = max(float(mine["x"].max() - mine["x"].min()), MIN_BOX_M)
            size_y = max(float(mine["y"].max() - mine["y"].min()), MIN_BOX_M)
            obj = RecordedObject(**{**obj.__dict__, "size_x": size_x, "size_y": size_y})
        sized.append(obj)
    return tuple(sized)


def build_frame(profile: RadarProfile, *, tick: int, sequence: str, frame_index: int, labels: np.ndarray,
                ra_labels: np.ndarray, rd_labels: np.ndarray, objects: tuple[RecordedObject, ...],
                log_power: np.ndarray | None = None) -> PredictionFrame:
    """A frame from a prediction's arrays: ``labels`` (R, A, D), its RA / RD masks, its objects and, when at hand,
    the cube's ``log_power`` (R, A, D) dB (the RA view is its max over Doppler, the RD view its max over angle)."""
    points = labelled_points(labels, profile, objects, log_power)
    ra_db = rd_db = None
    if log_power is not None:
        ra_db = log_power.max(axis=2).astype(np.float32)
        rd_db = log_power.max(axis=1).astype(np.float32)
    time_ns = round(tick * profile.frame_period_s * 1e9)
    return PredictionFrame(tick, time_ns, sequence, frame_index, points, with_extents(objects, points),
                           np.ascontiguousarray(ra_labels, np.uint8), np.ascontiguousarray(rd_labels, np.uint8),
                           ra_db, rd_db)


@contextlib.contextmanager
def binary_output(out: str | Path | IO[bytes]) -> Iterator[IO[bytes]]:
    """``out`` as a binary file object: a path opened for writing (and closed at the end), a file object as given."""
    if not isinstance(out, str | Path):
        yield out
        return
    with open(out, "wb") as stream:
        yield stream
