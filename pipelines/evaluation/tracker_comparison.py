"""Trackers compared on the same objects: ours (:mod:`radar.tracking`) and Stone Soup's
(:mod:`pipelines.evaluation.stonesoup_trackers`), each run over every sequence of an evaluation on the objects the
network found, scored against the simulator's tracks the way the field scores trackers.

A tracker's answer after a frame is the set of tracks it reports (ours: confirmed tracks, coasted ones included;
Stone Soup's: the tracks its tracker holds, a PHD track while its component weighs more than the extraction
threshold), each at its filtered position and velocity. Scores, class agnostic, at the evaluation's match distance
``c`` (:func:`pipelines.evaluation.tracking.match_distances`, 2 m for every built-in preset):

- GOSPA (:mod:`pipelines.evaluation.gospa`, alpha 2, order ``GOSPA_P``, cut-off ``c``): mean per frame (m), with its
  localisation, missed and false parts, and its mean at each frame position of a sequence (the plot);
- HOTA, DetA, AssA, LocA from TrackEval's ``HOTA`` with the similarity ``max(0, 1 - d / c)`` of a truth and a track
  ``d`` metres apart (the mean over TrackEval's 19 thresholds, as it reports them);
- MOTA, MOTP, IDF1, ID switches from py-motmetrics within ``c`` (as the ``tracking`` section);
- the velocity error of matched tracks against the simulator's (RMSE of vx, vy; heading), from a track's
  ``VELOCITY_MIN_AGE``-th frame on (its age counted as if confirmed at its earliest: ``confirm_hits - 1`` frames
  before its first report);
- milliseconds per frame of the tracker's step.

Stone Soup and TrackEval come with the ``tracking`` extra (``pip install -e '.[tracking]'``); serving needs neither.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pipelines.evaluation.gospa import gospa
from pipelines.evaluation.tracking import (
    Hypotheses,
    TrackingFrame,
    TruthObjects,
    json_number,
    milliseconds_summary,
    mot_accumulator,
    mot_summary,
    velocity_errors,
)
from radar.errors import UserError
from radar.tracking import Measurements, Tracker, TrackerConfig

GOSPA_P = 1.0  # GOSPA's order: errors in metres, a large one not weighed more than its size


class FrameTracker(Protocol):
    def step(self, measurements: Measurements, *, frames: int = 1) -> tuple[list[Hashable], np.ndarray, np.ndarray]:
        """Take one frame's objects (``frames`` periods after the last); the tracks reported after it: ids,
        positions (M, 2) in metres, velocities (M, 2) in m/s."""


class OursReported:
    """Our tracker (:class:`radar.tracking.Tracker`) reporting its confirmed tracks (coasted ones included)."""

    def __init__(self, config: TrackerConfig) -> None:
        self.tracker = Tracker(config)

    def step(self, measurements: Measurements, *, frames: int = 1) -> tuple[list[Hashable], np.ndarray, np.ndarray]:
        tracks = self.tracker.step(measurements, frames=frames).confirmed
        means = np.array([t.mean for t in tracks], np.float64).reshape(-1, 4)
        return [t.id for t in tracks], means[:, :2], means[:, 2:]


def _stonesoup(kind: str) -> Callable[..., FrameTracker]:
    def build(config: TrackerConfig, **settings: Any) -> FrameTracker:
        try:
            from pipelines.evaluation.stonesoup_trackers import TUNED, StoneSoupTracker
            return StoneSoupTracker(kind, config, replace(TUNED[kind], **settings))
        except ModuleNotFoundError as error:
            raise UserError(f"tracker stonesoup-{kind} needs Stone Soup ({error}): pip install -e '.[tracking]'") \
                from error
    return build


TRACKERS: dict[str, Callable[..., FrameTracker]] = {  # name -> builder(config, **its settings)
    "radarseg": OursReported,
    "stonesoup-gnn": _stonesoup("gnn"),
    "stonesoup-jpda": _stonesoup("jpda"),
    "stonesoup-gmphd": _stonesoup("gmphd"),
}


def parse_trackers(text: str) -> tuple[str, ...]:
    """``radarseg,stonesoup-gnn`` -> the names, each checked (ValueError naming the known ones)."""
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = [name for name in names if name not in TRACKERS]
    if unknown or not names:
        raise ValueError(f"trackers must be a comma-separated list of {', '.join(TRACKERS)}, got {text!r}")
    return names


@dataclass(frozen=True)
class TrackerRun:
    """One tracker over every sequence: its answers per sequence and frame, and the seconds of each step."""

    answers: dict[int, list[Hypotheses]]
    seconds: list[float]
    settings: dict[str, Any]  # the settings it was built with (Stone Soup's; {} for ours: TrackerConfig)


def run_reported(sequences: dict[int, list[TrackingFrame]], name: str, config: TrackerConfig,
                 settings: dict[str, Any] | None = None) -> TrackerRun:
    """Tracker ``name`` (built with ``settings``: Stone Soup's :class:`StoneSoupSettings` fields) over each
    sequence's predicted objects (a new tracker per sequence)."""
    answers: dict[int, list[Hypotheses]] = {}
    seconds: list[float] = []
    used: dict[str, Any] = {}
    for s, group in sequences.items():
        tracker = TRACKERS[name](config, **(settings or {}))
        used = asdict(tracker.settings) if hasattr(tracker, "settings") else {}
        ids: dict[Hashable, int] = {}  # a tracker's ids (Stone Soup's are strings) -> 1, 2, ...
        reported: dict[int, int] = {}  # frames each track was reported in
        answers[s], previous = [], None
        for frame in group:
            gap = 1 if previous is None else frame.frame_index - previous
            started = time.perf_counter()
            track_ids, xy, velocity = tracker.step(frame.predicted, frames=gap)
            seconds.append(time.perf_counter() - started)
            previous = frame.frame_index
            numbers = np.array([ids.setdefault(t, len(ids) + 1) for t in track_ids], np.int64)
            for n in numbers.tolist():
                reported[n] = reported.get(n, 0) + 1
            answers[s].append(Hypotheses(
                track_id=numbers, class_id=np.zeros(len(numbers), np.int64),
                xy=np.asarray(xy, np.float64).reshape(-1, 2),
                velocity=np.asarray(velocity, np.float64).reshape(-1, 2),
                age=np.array([reported[n] + config.confirm_hits - 1 for n in numbers.tolist()], np.int64),
                confirmed=np.ones(len(numbers), bool)))
    return TrackerRun(answers, seconds, used)


def compare_trackers(sequences: dict[int, list[TrackingFrame]], names: tuple[str, ...], config: TrackerConfig,
                     class_names: tuple[str, ...], match_m: float,
                     settings: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The ``trackers`` part of the tracking section: each tracker's scores (module docstring); ``settings[name]``
    builds tracker ``name``."""
    out: dict[str, Any] = {"names": list(names), "gospa": {"p": GOSPA_P, "alpha": 2, "c_m": match_m},
                           "hota_similarity": f"max(0, 1 - d / {match_m:g} m)", "reported": _REPORTED}
    for name in names:
        run = run_reported(sequences, name, config, (settings or {}).get(name))
        out[name] = {
            "settings": run.settings,
            "gospa": gospa_scores(sequences, run.answers, match_m),
            "hota": hota_scores(sequences, run.answers, match_m),
            "mot": mot_summary(mot_accumulator(sequences, run.answers, "all_objects", match_m, None)),
            "velocity": velocity_errors(sequences, run.answers, class_names, match_m)["overall"],
            "tracker_ms_per_frame": milliseconds_summary(1000 * np.asarray(run.seconds)),
        }
    return out


_REPORTED = ("tracks a tracker reports after each frame at their filtered position: ours confirmed (coasted "
             "included), Stone Soup's held tracks (a PHD track above the extraction weight)")


def gospa_scores(sequences: dict[int, list[TrackingFrame]], answers: dict[int, list[Hypotheses]],
                 c: float) -> dict[str, Any]:
    """GOSPA per frame: its mean (m) and its parts' means over every frame, and its mean at each frame position."""
    rows, by_position = [], {}
    for s, group in sequences.items():
        for position, (frame, hyp) in enumerate(zip(group, answers[s], strict=True)):
            truth = np.column_stack([frame.truth.x, frame.truth.y])
            g = gospa(truth, hyp.xy, c=c, p=GOSPA_P)
            rows.append((g.distance, g.localisation, g.missed, g.false, g.n_missed, g.n_false))
            by_position.setdefault(position, []).append(g.distance)
    if not rows:
        return {}
    a = np.asarray(rows, np.float64)
    return {"mean_m": json_number(a[:, 0].mean()), "localisation_mean": json_number(a[:, 1].mean()),
            "missed_mean": json_number(a[:, 2].mean()), "false_mean": json_number(a[:, 3].mean()),
            "missed_per_frame": json_number(a[:, 4].mean()), "false_per_frame": json_number(a[:, 5].mean()),
            "frames": len(a),
            "mean_by_frame_position": [json_number(np.mean(by_position[k])) for k in sorted(by_position)]}


def hota_scores(sequences: dict[int, list[TrackingFrame]], answers: dict[int, list[Hypotheses]],
                c: float) -> dict[str, Any]:
    """HOTA, DetA, AssA, LocA (means over TrackEval's thresholds) over every sequence, similarity
    ``max(0, 1 - d / c)``."""
    try:
        from trackeval.metrics import HOTA
    except ModuleNotFoundError as error:
        raise UserError(f"HOTA needs TrackEval ({error}): pip install -e '.[tracking]'") from error

    metric = HOTA()
    per_sequence = {str(s): metric.eval_sequence(_hota_data(group, answers[s], c)) for s, group in sequences.items()}
    combined = metric.combine_sequences(per_sequence)
    return {name.lower(): json_number(float(np.mean(combined[name]))) for name in ("HOTA", "DetA", "AssA", "LocA")}


def _hota_data(group: list[TrackingFrame], answers: list[Hypotheses], c: float) -> dict[str, Any]:
    """One sequence as TrackEval's ``eval_sequence`` reads it: ids 0, 1, ... per sequence, similarity per frame."""
    truth_ids = {int(t): k for k, t in enumerate(sorted({int(t) for f in group for t in f.truth.track_id}))}
    track_ids = {int(t): k for k, t in enumerate(sorted({int(t) for h in answers for t in h.track_id}))}
    data: dict[str, Any] = {"gt_ids": [], "tracker_ids": [], "similarity_scores": [],
                            "num_gt_ids": len(truth_ids), "num_tracker_ids": len(track_ids)}
    for frame, hyp in zip(group, answers, strict=True):
        data["gt_ids"].append(np.array([truth_ids[int(t)] for t in frame.truth.track_id], np.int64))
        data["tracker_ids"].append(np.array([track_ids[int(t)] for t in hyp.track_id], np.int64))
        d = np.hypot(frame.truth.x[:, None] - hyp.xy[None, :, 0], frame.truth.y[:, None] - hyp.xy[None, :, 1])
        data["similarity_scores"].append(np.clip(1 - d / c, 0, None))
    data["num_gt_dets"] = sum(len(ids) for ids in data["gt_ids"])
    data["num_tracker_dets"] = sum(len(ids) for ids in data["tracker_ids"])
    return data


def plot_gospa_by_frame(comparison: dict[str, Any], path: str | Path) -> str:
    """A PNG of each tracker's mean GOSPA (m) at each frame position of a sequence; the file's name."""
    from pipelines.figures import plt, save_figure

    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for name in comparison["names"]:
        scores = comparison[name]["gospa"]
        if scores:
            by_frame = np.array(scores["mean_by_frame_position"], np.float64)
            ax.plot(np.arange(1, len(by_frame) + 1), by_frame, marker="o", markersize=3,
                    label=f"{name} (mean {scores['mean_m']:.2f} m)")
    g = comparison["gospa"]
    ax.set(xlabel="frame of the sequence", ylabel=f"GOSPA (m; p = {g['p']:g}, c = {g['c_m']:g} m, alpha = 2)",
           title="GOSPA per frame, mean over the sequences")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path).name


_TRUTH_FIELDS = ("track_id", "class_id", "x", "y", "vx", "vy", "radial_velocity")
_OBJECT_FIELDS = ("x", "y", "radial_velocity", "class_id", "score")


def save_frames(frames: list[TrackingFrame], path: str | Path) -> Path:
    """The frames' truth and objects as one ``.npz`` (rows of every frame concatenated, counts per frame), so that
    trackers can be compared or tuned again without the network (:func:`load_frames`)."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "sequence_id": np.array([f.sequence_id for f in frames], np.int64),
        "frame_index": np.array([f.frame_index for f in frames], np.int64),
        "n_truth": np.array([len(f.truth.x) for f in frames], np.int64),
        "n_objects": np.array([len(f.predicted) for f in frames], np.int64)}
    for name in _TRUTH_FIELDS:
        arrays[f"truth_{name}"] = np.concatenate([[], *(getattr(f.truth, name) for f in frames)])
    for name in _OBJECT_FIELDS:
        arrays[f"objects_{name}"] = np.concatenate([[], *(getattr(f.predicted, name) for f in frames)])
    np.savez_compressed(path, **arrays)
    return path


def load_frames(path: str | Path) -> list[TrackingFrame]:
    """The frames :func:`save_frames` wrote (ValueError naming what is missing from another file)."""
    with np.load(path) as data:
        missing = {"sequence_id", "frame_index", "n_truth", "n_objects"} - set(data.files)
        if missing:
            raise ValueError(f"{path} is not a file of tracking frames (save_frames): it lacks {sorted(missing)}")
        arrays = {name: data[name] for name in data.files}
    truth_at = np.concatenate([[0], np.cumsum(arrays["n_truth"])])
    objects_at = np.concatenate([[0], np.cumsum(arrays["n_objects"])])
    frames = []
    for k, (s, i) in enumerate(zip(arrays["sequence_id"], arrays["frame_index"], strict=True)):
        t, o = slice(truth_at[k], truth_at[k + 1]), slice(objects_at[k], objects_at[k + 1])
        truth = TruthObjects(**{name: arrays[f"truth_{name}"][t].astype(np.int64 if name.endswith("_id") else float)
                                for name in _TRUTH_FIELDS})
        objects = Measurements(**{name: arrays[f"objects_{name}"][o].astype(np.int64 if name == "class_id" else float)
                                  for name in _OBJECT_FIELDS})
        frames.append(TrackingFrame(int(s), int(i), truth, objects))
    return frames
