"""Tracking evaluation: the tracker (:mod:`radar.tracking`) over a store's sequences, scored against the
simulator's tracks (docs/design.md section 16).

Frames are grouped by sequence and taken in ``frame_index`` order; one tracker per sequence, and a gap in
``frame_index`` (frames left out, e.g. by ``--max-frames``) is one step of ``frames=k``. The tracker runs twice:

- ``predicted``: on the objects the network found in each frame (``EraseNet.segment(...).objects``);
- ``truth_centres``: on the store's object table (labelled centre, radial velocity of its Doppler bin,
  class, score 1): the tracker's own bound, with perfect detection.

Ground truth is the object table's ``track_id`` at its centre ``(x, y)``. Hypotheses are the objects at
their own position, each labelled with the id of its track, in two variants: ``all_objects`` (every object
of a frame with the id of the track it went to, new tracks included) and ``confirmed`` (only objects whose
track is confirmed after that frame: what a consumer of confirmed tracks sees). CLEAR MOT and identity
metrics come from py-motmetrics with a Euclidean match distance in Cartesian metres (``MATCH_DISTANCE_M``,
and ``SECONDARY_DISTANCE_M``, set for the 50 m road radars and scaled to the radar by
:func:`radar.profiles.scene_settings.radar_scale` like the AP distances: :func:`match_distances`), overall (class
agnostic) and per class (truth of the class against tracks voted that class). Scores at a distance ``d`` are under
the key :func:`match_key` (``match_2m`` for every built-in preset). The velocity error compares a matched track's
velocity vector with the simulator's from the track's ``VELOCITY_MIN_AGE``-th frame on; heading only for objects
faster than ``HEADING_MIN_SPEED_MPS``.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from radar.profiles import RadarProfile
from radar.profiles.scene_settings import radar_scale
from radar.tracking import Measurements, Tracker, TrackerConfig, TrackStatus

MATCH_DISTANCE_M = 2.0  # metres, for a radar of 50 m or more (match_distances scales both to the radar)
SECONDARY_DISTANCE_M = 1.0
VELOCITY_MIN_AGE = 3  # a track's third frame on
HEADING_MIN_SPEED_MPS = 1.0
SOURCES = ("predicted", "truth_centres")
VARIANTS = {"all_objects": "every object of a frame, with the id of the track it was assigned to (new tracks too)",
            "confirmed": "only the objects whose track is confirmed after that frame"}
MOT_METRICS = ("mota", "motp", "idf1", "idp", "idr", "precision", "recall", "num_switches", "num_fragmentations",
               "mostly_tracked", "partially_tracked", "mostly_lost", "num_unique_objects", "num_false_positives",
               "num_misses", "num_objects", "num_predictions")


def match_distances(profile: RadarProfile) -> tuple[float, float]:
    """The match distance and the secondary one (m) for ``profile``: ``MATCH_DISTANCE_M`` and
    ``SECONDARY_DISTANCE_M`` times :func:`radar_scale`, to the millimetre (they name keys: :func:`match_key`).
    2 and 1 m for every built-in preset, 0.25 and 0.125 m for OpenRadar's radar (6.246 m)."""
    scale = radar_scale(profile)
    return round(MATCH_DISTANCE_M * scale, 3), round(SECONDARY_DISTANCE_M * scale, 3)


def match_key(distance_m: float) -> str:
    """The key of the scores at match distance ``distance_m`` (m) in a variant's section: ``match_2m``."""
    return f"match_{distance_m:g}m"


@dataclass(frozen=True)
class TruthObjects:
    """The labelled objects of one frame from the store's object table: track id, class, centre (m), velocity
    vector (m/s) and the radial velocity of the Doppler bin (m/s)."""

    track_id: np.ndarray
    class_id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    radial_velocity: np.ndarray

    @classmethod
    def from_table(cls, table: np.ndarray, profile: RadarProfile) -> TruthObjects:
        """From the rows in use of a frame's object table (columns ``OBJECT_FIELDS``, with tracking truth)."""
        from pipelines.datasets.store import OBJECT_COLUMN as col  # torch and zarr: not for evaluate --help
        table = np.asarray(table, np.float64)
        return cls(table[:, col["track_id"]].astype(np.int64), table[:, col["class_id"]].astype(np.int64),
                   table[:, col["x"]], table[:, col["y"]], table[:, col["vx"]], table[:, col["vy"]],
                   np.asarray(profile.velocity_mps(table[:, col["doppler_bin"]]), np.float64))

    def measurements(self) -> Measurements:
        """The true centres as the tracker's input (score 1)."""
        return Measurements(self.x, self.y, self.radial_velocity, self.class_id, np.ones(len(self.x)))


@dataclass(frozen=True)
class TrackingFrame:
    """What tracking needs of one evaluated frame."""

    sequence_id: int
    frame_index: int
    truth: TruthObjects
    predicted: Measurements


@dataclass(frozen=True)
class Hypotheses:
    """The tracker's answer for the objects of one frame (one row per object): the object's position, its
    track's id, voted class, filtered velocity, age and whether it is confirmed after the frame."""

    track_id: np.ndarray
    class_id: np.ndarray
    xy: np.ndarray  # (N, 2) the object's own position (m): MOTP measures how objects are placed
    velocity: np.ndarray  # (N, 2) its track's (m/s)
    age: np.ndarray
    confirmed: np.ndarray  # bool


class TrackingTally:
    """The frames of an evaluation as they come (any order), for :func:`evaluate_tracking` at the end; ``problem``
    says in one line why the store cannot be scored (no tracking truth), and then nothing is kept."""

    def __init__(self, profile: RadarProfile, problem: str | None = None) -> None:
        self.profile = profile
        self.problem = problem
        self.frames: list[TrackingFrame] = []

    def add(self, sequence_id: int, frame_index: int, table: np.ndarray, objects: list[Any]) -> None:
        """One frame: the rows in use of its object table and the network's objects."""
        if self.problem is not None:
            return
        from pipelines.datasets.store import OBJECT_COLUMN  # torch and zarr: not for evaluate --help

        if np.isnan(np.asarray(table, np.float64)[:, OBJECT_COLUMN["track_id"]]).any():
            self.problem = "the store's objects carry no track ids (its source records none): no tracking truth"
            self.frames = []
            return
        truth = TruthObjects.from_table(table, self.profile)
        self.frames.append(TrackingFrame(int(sequence_id), int(frame_index), truth, Measurements.from_objects(objects)))

    def summary(self, config: TrackerConfig | None = None) -> dict[str, Any]:
        if self.problem is not None:
            return {"skipped": self.problem}
        return evaluate_tracking(self.frames, self.profile, config)


def run_tracker(frames: list[TrackingFrame], source: str,
                config: TrackerConfig) -> tuple[list[Hypotheses], list[float]]:
    """One tracker over one sequence's frames (in ``frame_index`` order): the hypotheses of each frame and the
    seconds of each step."""
    tracker = Tracker(config)
    answers, seconds = [], []
    previous = None
    for frame in frames:
        measurements = frame.predicted if source == "predicted" else frame.truth.measurements()
        gap = 1 if previous is None else frame.frame_index - previous
        started = time.perf_counter()
        step = tracker.step(measurements, frames=gap)
        seconds.append(time.perf_counter() - started)
        previous = frame.frame_index
        rows = step.object_tracks
        answers.append(Hypotheses(
            track_id=step.track_ids.copy(), class_id=np.array([t.class_id for t in rows], np.int64),
            xy=np.column_stack([measurements.x, measurements.y]).astype(np.float64).reshape(-1, 2),
            velocity=np.array([t.mean[2:] for t in rows], np.float64).reshape(-1, 2),
            age=np.array([t.age for t in rows], np.int64),
            confirmed=np.array([t.status is TrackStatus.confirmed for t in rows], bool)))
    return answers, seconds


def by_sequence(frames: Iterable[TrackingFrame]) -> dict[int, list[TrackingFrame]]:
    """Frames grouped by sequence, each group in ``frame_index`` order."""
    groups: dict[int, list[TrackingFrame]] = defaultdict(list)
    for frame in frames:
        groups[frame.sequence_id].append(frame)
    return {s: sorted(group, key=lambda f: f.frame_index) for s, group in sorted(groups.items())}


def evaluate_tracking(frames: Iterable[TrackingFrame], profile: RadarProfile,
                      config: TrackerConfig | None = None) -> dict[str, Any]:
    """The ``tracking`` section of metrics.json for these frames (any order)."""
    config = config or TrackerConfig.for_profile(profile)
    match_m, secondary_m = match_distances(profile)
    sequences = by_sequence(frames)
    truth_ids = {(s, int(t)) for s, group in sequences.items() for f in group for t in f.truth.track_id}
    section: dict[str, Any] = {
        "match_distance_m": match_m, "secondary_distance_m": secondary_m,
        "distance": "Euclidean, Cartesian x-y (m); a pair farther apart never matches",
        "variants": VARIANTS, "velocity_min_age": VELOCITY_MIN_AGE, "heading_min_speed_mps": HEADING_MIN_SPEED_MPS,
        "sequences": len(sequences), "frames": sum(len(g) for g in sequences.values()),
        "truth_tracks": len(truth_ids), "config": config.to_dict(),
    }
    class_names = profile.class_names
    for source in SOURCES:
        answers, seconds = {}, []
        for s, group in sequences.items():
            answers[s], step_seconds = run_tracker(group, source, config)
            seconds += step_seconds
        result: dict[str, Any] = {}
        for variant in VARIANTS:
            result[variant] = {match_key(d): _mot_scores(sequences, answers, variant, d, class_names)
                               for d in (match_m, secondary_m)}
        result["velocity"] = velocity_errors(sequences, answers, class_names, match_m)
        ms = 1000 * np.asarray(seconds)
        result["tracker_ms_per_frame"] = milliseconds_summary(ms)
        section[source] = result
    return section


def _distances(truth_xy: np.ndarray, hyp_xy: np.ndarray, max_distance: float) -> np.ndarray:
    d = np.hypot(truth_xy[:, None, 0] - hyp_xy[None, :, 0], truth_xy[:, None, 1] - hyp_xy[None, :, 1])
    return np.where(d <= max_distance, d, np.nan)


_ID_STRIDE = 1_000_000  # ids and frame numbers of sequence s are s * _ID_STRIDE + its own: one accumulator


def mot_accumulator(sequences: dict[int, list[TrackingFrame]], answers: dict[int, list[Hypotheses]], variant: str,
                 distance: float, class_id: int | None) -> Any:
    """One motmetrics accumulator over every sequence (ids and frames made unique per sequence), of one class
    (truth of that class against tracks voted it) or of every class (``None``)."""
    import motmetrics as mm

    acc = mm.MOTAccumulator(auto_id=False)
    for s, group in sequences.items():
        base = s * _ID_STRIDE
        for frame, hyp in zip(group, answers[s], strict=True):
            t_keep = np.ones(len(frame.truth.x), bool) if class_id is None else frame.truth.class_id == class_id
            h_keep = hyp.confirmed.copy() if variant == "confirmed" else np.ones(len(hyp.track_id), bool)
            if class_id is not None:
                h_keep &= hyp.class_id == class_id
            truth_xy = np.column_stack([frame.truth.x, frame.truth.y])[t_keep]
            acc.update((base + frame.truth.track_id[t_keep]).tolist(), (base + hyp.track_id[h_keep]).tolist(),
                       _distances(truth_xy, hyp.xy[h_keep], distance), frameid=base + frame.frame_index)
    return acc


def _mot_scores(sequences: dict[int, list[TrackingFrame]], answers: dict[int, list[Hypotheses]], variant: str,
                distance: float, class_names: tuple[str, ...]) -> dict[str, Any]:
    """CLEAR MOT and identity metrics, overall and per class."""
    out = {"overall": mot_summary(mot_accumulator(sequences, answers, variant, distance, None))}
    out["per_class"] = {name: mot_summary(mot_accumulator(sequences, answers, variant, distance, c))
                        for c, name in enumerate(class_names, start=1)}
    return out


def mot_summary(acc: Any) -> dict[str, Any]:
    import motmetrics as mm

    row = mm.metrics.create().compute(acc, metrics=list(MOT_METRICS), name="all").iloc[0]
    summary = {name: json_number(row[name]) for name in MOT_METRICS}
    for name in MOT_METRICS:
        if name.startswith(("num_", "mostly_", "partially_")) and summary[name] is not None:
            summary[name] = int(summary[name])
    tracks = summary["num_unique_objects"] or 0
    summary["switches_per_100_tracks"] = json_number(100 * summary["num_switches"] / tracks) if tracks else None
    return summary


def velocity_errors(sequences: dict[int, list[TrackingFrame]], answers: dict[int, list[Hypotheses]],
                     class_names: tuple[str, ...], match_m: float) -> dict[str, Any]:
    """RMSE of vx, vy (m/s) and heading (degrees) of tracks matched to truth (``all_objects`` hypotheses within
    ``match_m`` metres), from the track's ``VELOCITY_MIN_AGE``-th frame on, per class of the truth."""
    pairs: dict[int, list[tuple[float, float, float, float]]] = defaultdict(list)  # class -> (dvx, dvy, true v)
    for s, group in sequences.items():
        events = mot_accumulator({s: group}, {s: answers[s]}, "all_objects", match_m, None).mot_events
        matched = events[events["Type"].isin(["MATCH", "SWITCH"])]
        frames = {f.frame_index: (f, h) for f, h in zip(group, answers[s], strict=True)}
        for (frame_index, _), event in matched.iterrows():
            frame, hyp = frames[int(frame_index) - s * _ID_STRIDE]
            t = int(np.flatnonzero(frame.truth.track_id == int(event["OId"]) - s * _ID_STRIDE)[0])
            h = int(np.flatnonzero(hyp.track_id == int(event["HId"]) - s * _ID_STRIDE)[0])
            if hyp.age[h] < VELOCITY_MIN_AGE or not np.isfinite(frame.truth.vx[t]):
                continue
            true_v = np.array([frame.truth.vx[t], frame.truth.vy[t]])
            pairs[int(frame.truth.class_id[t])].append((*(hyp.velocity[h] - true_v), *true_v))
    out = {"overall": _rmse([p for rows in pairs.values() for p in rows])}
    out["per_class"] = {name: _rmse(pairs.get(c, [])) for c, name in enumerate(class_names, start=1)}
    return out


def _rmse(rows: list[tuple[float, float, float, float]]) -> dict[str, Any]:
    """RMSE of vx, vy and of heading (objects faster than HEADING_MIN_SPEED_MPS) over (dvx, dvy, vx, vy) rows."""
    if not rows:
        return {"vx_rmse_mps": None, "vy_rmse_mps": None, "heading_rmse_deg": None, "n": 0, "n_heading": 0}
    a = np.asarray(rows, np.float64)
    true_v, estimate = a[:, 2:], a[:, :2] + a[:, 2:]
    fast = np.hypot(true_v[:, 0], true_v[:, 1]) > HEADING_MIN_SPEED_MPS
    heading = np.arctan2(estimate[fast, 1], estimate[fast, 0]) - np.arctan2(true_v[fast, 1], true_v[fast, 0])
    heading = np.degrees((heading + np.pi) % (2 * np.pi) - np.pi)
    return {"vx_rmse_mps": json_number(np.sqrt(np.mean(a[:, 0] ** 2))),
            "vy_rmse_mps": json_number(np.sqrt(np.mean(a[:, 1] ** 2))),
            "heading_rmse_deg": json_number(np.sqrt(np.mean(heading**2))) if fast.any() else None,
            "n": len(a), "n_heading": int(fast.sum())}


def milliseconds_summary(ms: np.ndarray) -> dict[str, Any]:
    """Mean, median and 99th percentile of per-frame milliseconds, and the frames counted ({} for none)."""
    if not len(ms):
        return {}
    return {"mean": json_number(ms.mean()), "median": json_number(np.median(ms)),
            "p99": json_number(np.percentile(ms, 99)), "frames": len(ms)}


def json_number(value: Any) -> float | int | None:
    """A JSON number (None for NaN)."""
    value = value.item() if hasattr(value, "item") else value
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
