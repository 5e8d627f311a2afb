"""Tracks as priors of the next frame's detection (docs/guides/tracking.md, "Tracks as priors").

A confirmed track predicts where its object will be in the next frame (:meth:`radar.tracking.Tracker.
predicted_positions`). A missed detection on such a track is a missed object, often one the detector saw but scored
under its operating threshold (a slow, small, far pedestrian beside the zero-Doppler clutter). Where a prediction
has no centre above the operating score within ``gate_m``, the best centre the detector decoded within the gate at
a lower score (``threshold``) seeds region growing like any other centre, and the segmenter decides: a seed whose
region holds no foreground voxel makes no object. Nothing is added where no track predicts an object, so a frame
without history is segmented as before. Off unless asked for (``threshold`` None everywhere).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radar.centres import Centres
from radar.profiles import RadarProfile
from radar.tracking import Measurements, Tracker, TrackerConfig, TrackerStep

PRIOR_GATE_M = 3.0
"""Distance (m) between a track's predicted position and a centre that may stand for it (a built-in radar's)."""


@dataclass(frozen=True)
class TrackPriorsConfig:
    """``threshold``: the heatmap score a centre near a track's prediction needs (below the detector's operating
    score to add anything); ``gate_m``: how near (m)."""

    threshold: float
    gate_m: float = PRIOR_GATE_M

    def __post_init__(self) -> None:
        if not (isinstance(self.threshold, int | float) and 0 < self.threshold < 1):
            raise ValueError(f"the track priors' threshold must be a score in (0, 1), got {self.threshold!r}")
        if not (isinstance(self.gate_m, int | float) and np.isfinite(self.gate_m) and self.gate_m > 0):
            raise ValueError(f"the track priors' gate must be a finite distance > 0 (m), got {self.gate_m!r}")


@dataclass(frozen=True)
class TrackPriors:
    """Where a frame's confirmed tracks expect their objects: ``positions`` (T, 2) x, y in metres."""

    positions: np.ndarray
    config: TrackPriorsConfig

    def __post_init__(self) -> None:
        positions = np.asarray(self.positions, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != 2 or not np.isfinite(positions).all():
            raise ValueError(f"track priors' positions must be finite (T, 2) x, y, got shape {positions.shape}")
        object.__setattr__(self, "positions", positions)


def centres_with_priors(candidates: Centres, score_threshold: float, priors: TrackPriors | None,
                        profile: RadarProfile) -> tuple[Centres, int]:
    """The centres a frame keeps: every candidate scored at least ``score_threshold``, and for each prior with
    none of those within its gate, the best-scored other candidate within it at ``priors.config.threshold`` or
    more (each candidate stands for one prior at most). ``candidates`` are sorted by descending score (a
    detector's decoding); so is the result. Returns the centres and how many the priors added."""
    strong = candidates.score >= score_threshold
    if (priors is None or not len(priors.positions)) and strong.all():
        return candidates, 0  # the request path without priors: nothing to filter, nothing copied
    chosen = np.zeros(len(candidates), bool)
    if priors is not None and len(priors.positions) and len(candidates):
        x, y = profile.xy(candidates.range_bin, candidates.angle_bin)
        near = np.hypot(x[None] - priors.positions[:, :1], y[None] - priors.positions[:, 1:]) <= priors.config.gate_m
        weak = ~strong & (candidates.score >= priors.config.threshold)
        for row in near:
            if (row & strong).any():
                continue
            free = np.flatnonzero(row & weak & ~chosen)
            if len(free):  # sorted by score: the first is the best
                chosen[free[0]] = True
    keep = strong | chosen
    kept = Centres(candidates.score[keep], candidates.range_bin[keep], candidates.angle_bin[keep],
                   candidates.doppler_bin[keep])
    return kept, int(chosen.sum())


@dataclass
class SequenceTracks:
    """One tracker per sequence, stepped as its frames are segmented in order: :meth:`priors` before a frame,
    :meth:`step` with its objects after. What ``evaluate --track-priors`` and ``segment-batch --track-priors`` run."""

    tracker_config: TrackerConfig
    priors_config: TrackPriorsConfig
    _trackers: dict[Any, tuple[Tracker, int]] = field(default_factory=dict)

    def priors(self, sequence: Any, frame_index: int) -> TrackPriors | None:
        """The priors of ``sequence``'s frame ``frame_index``: None for its first frame."""
        if sequence not in self._trackers:
            return None
        tracker, last = self._trackers[sequence]
        return TrackPriors(tracker.predicted_positions(frames=self._gap(last, frame_index)), self.priors_config)

    def step(self, sequence: Any, frame_index: int, objects: list[Any]) -> TrackerStep:
        """Take the frame's objects (ERASE-Net's :class:`~models.erasenet.model.SegmentedObject` or anything with
        ``x``, ``y``, ``velocity_mps``, ``class_id`` and ``score``)."""
        if sequence in self._trackers:
            tracker, last = self._trackers[sequence]
            frames = self._gap(last, frame_index)
        else:
            tracker, frames = Tracker(self.tracker_config), 1
        step = tracker.step(Measurements.from_objects(objects), frames=frames)
        self._trackers[sequence] = (tracker, int(frame_index))
        return step

    @staticmethod
    def _gap(last: int, frame_index: int) -> int:
        if frame_index <= last:
            raise ValueError(f"frames of a sequence must come in order: frame {frame_index} after frame {last}")
        return int(frame_index - last)
