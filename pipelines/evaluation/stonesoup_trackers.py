"""Stone Soup's trackers as baselines of ours (:mod:`radar.tracking`), on the same objects and with the same models.

Three trackers people compare radar trackers with, built from Stone Soup's own components
(``pip install -e '.[tracking]'``):

- ``stonesoup-gnn``: global nearest neighbour (``GNNWith2DAssignment``, Mahalanobis distance) in a
  ``MultiTargetTracker``;
- ``stonesoup-jpda``: joint probabilistic data association (``JPDA`` over ``PDAHypothesiser``) in a
  ``MultiTargetMixtureTracker``;
- ``stonesoup-gmphd``: a Gaussian-mixture PHD filter (``PHDUpdater``, ``GaussianMixtureReducer``) in a
  ``PointProcessMultiTargetTracker``, a track per component tag.

Each is given what ours is given (:class:`radar.tracking.TrackerConfig` from the profile): an extended Kalman filter
with a constant-velocity motion model (Stone Soup's ``ConstantVelocity``, driven by continuous white noise: its ``q
= acceleration_sigma^2 * frame_period`` gives ours' velocity variance per frame for the same acceleration noise,
which is tuned for each, as ours was), and a measurement of bearing, range and radial velocity
(``CartesianToBearingRangeRate2D``) with ours' noise per object: range ``max(range_sigma_m, min_position_sigma_m)``,
bearing ``max(azimuth_sigma_rad * r, min_position_sigma_m) / r``, radial velocity ``radial_velocity_sigma_mps``. A
track is confirmed after ``confirm_hits`` updates (``MultiMeasurementInitiator``), a tentative one is dropped after
``tentative_max_misses`` + 1 frames without one and a confirmed one after ``max_misses`` + 1
(``UpdateTimeStepsDeleter``); the association gate is ours (``gate_chi2``). What ours has that they have not: the
radial velocity's innovation wrapped into the unambiguous interval, the gate in metres, a class's typical speed as a
new track's prior.

Their own settings (clutter, detection probability, the PHD's birth and extraction, and their acceleration noise) were
tuned for GOSPA on a tuning seed: :data:`TUNED`.

Stone Soup runs its trackers as iterators over a detection reader; :class:`StoneSoupTracker` feeds it one frame at a
time so that it is stepped like ours.
"""

from __future__ import annotations

import datetime
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.dataassociator.probability import JPDA
from stonesoup.deleter.time import UpdateTimeStepsDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.hypothesiser.gaussianmixture import GaussianMixtureHypothesiser
from stonesoup.hypothesiser.probability import PDAHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.mixturereducer.gaussianmixture import GaussianMixtureReducer
from stonesoup.models.base import ReversibleModel
from stonesoup.models.measurement.nonlinear import CartesianToBearingRangeRate2D
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.kalman import ExtendedKalmanPredictor
from stonesoup.tracker.pointprocess import PointProcessMultiTargetTracker
from stonesoup.tracker.simple import MultiTargetMixtureTracker, MultiTargetTracker
from stonesoup.types.angle import Bearing
from stonesoup.types.array import StateVector
from stonesoup.types.detection import Detection
from stonesoup.types.state import GaussianState, TaggedWeightedGaussianState
from stonesoup.updater.kalman import ExtendedKalmanUpdater
from stonesoup.updater.pointprocess import PHDUpdater

from radar.tracking import Measurements, TrackerConfig

EPOCH = datetime.datetime(2000, 1, 1)


@dataclass(frozen=True)
class StoneSoupSettings:
    """What the baselines need beyond :class:`TrackerConfig`: the clutter and detection model of JPDA and the PHD
    filter (clutter per frame over the field of view, the probability of detecting an object) and the PHD filter's
    birth, survival and extraction."""

    clutter_per_frame: float = 1.0  # false objects per frame, spread uniformly over bearing, range, radial velocity
    prob_detect: float = 0.8
    prob_gate: float = 0.999  # JPDA's gate probability
    prob_survival: float = 0.95
    birth_weight: float = 0.3  # expected new objects per frame (the PHD's birth component)
    extraction_threshold: float = 0.5  # a PHD component reported as a track above this weight
    merge_threshold: float = 16.0  # squared Mahalanobis distance under which PHD components merge
    prune_threshold: float = 1e-6
    max_range_m: float = 50.0  # the ranges clutter spreads over and the PHD's birth covers (the road presets')
    acceleration_sigma_mps2: float | None = None  # the motion noise, if tuned apart from ours (None: ours)


TUNED = {  # each tracker's settings, tuned for GOSPA on a tuning seed (experiments/studies/stonesoup_tuning.py)
    "gnn": StoneSoupSettings(acceleration_sigma_mps2=8.0),
    "jpda": StoneSoupSettings(clutter_per_frame=5.0, prob_detect=0.5, acceleration_sigma_mps2=12.0),
    "gmphd": StoneSoupSettings(clutter_per_frame=0.5, birth_weight=0.1, acceleration_sigma_mps2=8.0),
}


class BearingRangeRate(CartesianToBearingRangeRate2D, ReversibleModel):
    """Stone Soup's bearing, range and radial velocity made reversible for its initiator: a track starts at the
    object's position, moving at its radial velocity along the line of sight (the velocity across it from the
    initiator's prior), as ours starts its tracks."""

    def inverse_function(self, detection: Any, **kwargs: Any) -> StateVector:
        bearing, rho, rho_rate = (float(v) for v in detection.state_vector[:, 0])
        out = StateVector(np.zeros(self.ndim_state))
        out[self.mapping, 0] = rho * np.cos(bearing), rho * np.sin(bearing)
        out[self.velocity_mapping, 0] = rho_rate * np.cos(bearing), rho_rate * np.sin(bearing)
        return out


class _Feed:
    """A detection reader that yields what :meth:`put` was given, one frame a time."""

    def __init__(self) -> None:
        self.queue: deque = deque()

    def put(self, timestamp: datetime.datetime, detections: set) -> None:
        self.queue.append((timestamp, detections))

    def __iter__(self) -> _Feed:
        return self

    def __next__(self) -> tuple[datetime.datetime, set]:
        return self.queue.popleft()


class StoneSoupTracker:
    """One of Stone Soup's trackers stepped frame by frame: :meth:`step` takes a frame's objects and returns the
    tracks it reports after them (id, position (m), velocity (m/s))."""

    def __init__(self, kind: str, config: TrackerConfig, settings: StoneSoupSettings | None = None) -> None:
        if kind not in BUILDERS:
            raise ValueError(f"Stone Soup tracker kind must be one of {tuple(BUILDERS)}, got {kind!r}")
        self.config, self.settings = config, settings or TUNED[kind]
        self.feed = _Feed()
        self.frames = 0
        self.tracker = BUILDERS[kind](self.config, self.settings, self.feed)
        self.iterator = iter(self.tracker)
        self.is_phd = kind == "gmphd"

    def detections(self, measurements: Measurements, timestamp: datetime.datetime) -> set:
        """The frame's objects as Stone Soup detections, each with its own measurement noise."""

        cfg = self.config
        out = set()
        for x, y, radial_velocity in zip(measurements.x, measurements.y, measurements.radial_velocity, strict=True):
            r = max(float(np.hypot(x, y)), 1e-3)
            sigma_range = max(cfg.range_sigma_m, cfg.min_position_sigma_m)
            sigma_bearing = max(cfg.azimuth_sigma_rad * r, cfg.min_position_sigma_m) / r
            noise = np.diag([sigma_bearing**2, sigma_range**2, cfg.radial_velocity_sigma_mps**2])
            measurement_model = BearingRangeRate(ndim_state=4, mapping=(0, 2), velocity_mapping=(1, 3),
                                                 noise_covar=noise)
            out.add(Detection([[Bearing(np.arctan2(y, x))], [r], [float(radial_velocity)]], timestamp=timestamp,
                              measurement_model=measurement_model))
        return out

    def step(self, measurements: Measurements, *, frames: int = 1) -> tuple[list[str], np.ndarray, np.ndarray]:
        """Advance by ``frames`` frame periods and take this frame's objects; the reported tracks: ids, positions
        (M, 2) in metres and velocities (M, 2) in m/s."""
        self.frames += frames
        timestamp = EPOCH + datetime.timedelta(seconds=self.frames * self.config.frame_period_s)
        self.feed.put(timestamp, self.detections(measurements, timestamp))
        _, tracks = next(self.iterator)
        states = [(track.id, self._state(track, timestamp)) for track in tracks]
        states = [(track_id, state) for track_id, state in states if state is not None]
        ids = [track_id for track_id, _ in states]
        vectors = np.array([np.asarray(state.state_vector, np.float64)[:, 0] for _, state in states]).reshape(-1, 4)
        return ids, vectors[:, [0, 2]], vectors[:, [1, 3]]

    def _state(self, track: Any, timestamp: datetime.datetime) -> Any:
        """The track's state at ``timestamp`` it reports, or None: a PHD track is reported while a component of its
        tag at this time weighs more than the extraction threshold (its heaviest one)."""
        if not self.is_phd:
            return track.state
        now = [s for s in track.states if s.timestamp == timestamp]
        best = max(now, key=lambda s: float(s.weight), default=None)
        return best if best is not None and float(best.weight) > self.settings.extraction_threshold else None


# ----------------------------------------------------------------------------------------------- builders
def _components(config: TrackerConfig, settings: StoneSoupSettings) -> tuple[Any, Any, Any]:
    """The shared models: transition model, EKF predictor and updater (detections carry their measurement model)."""
    acceleration = settings.acceleration_sigma_mps2 or config.acceleration_sigma_mps2
    q = acceleration**2 * config.frame_period_s
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])
    return transition, ExtendedKalmanPredictor(transition), ExtendedKalmanUpdater(measurement_model=None)


def _initiator(config: TrackerConfig, predictor: Any, updater: Any) -> Any:
    """Tentative tracks held until ``confirm_hits`` updates, associated by GNN, started from one object each."""
    speed = config.initial_speed_sigma_mps
    prior = GaussianState(np.zeros((4, 1)), np.diag([0.0, speed**2, 0.0, speed**2]))
    hypothesiser = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(),
                                        missed_distance=float(np.sqrt(config.gate_chi2)))
    return MultiMeasurementInitiator(prior_state=prior, deleter=UpdateTimeStepsDeleter(config.tentative_max_misses + 1),
                                     data_associator=GNNWith2DAssignment(hypothesiser), updater=updater,
                                     min_points=config.confirm_hits)


def _clutter_density(config: TrackerConfig, settings: StoneSoupSettings) -> float:
    """False objects per unit of measurement space (rad x m x m/s): ``clutter_per_frame`` spread over the bearings
    in front (pi rad), the ranges up to ``max_range_m`` and the unambiguous radial velocities."""
    volume = np.pi * settings.max_range_m * 2 * config.max_radial_velocity_mps
    return settings.clutter_per_frame / volume


def _gnn(config: TrackerConfig, settings: StoneSoupSettings, feed: _Feed) -> Any:
    _, predictor, updater = _components(config, settings)
    hypothesiser = DistanceHypothesiser(predictor, updater, measure=Mahalanobis(),
                                        missed_distance=float(np.sqrt(config.gate_chi2)))
    return MultiTargetTracker(initiator=_initiator(config, predictor, updater),
                              deleter=UpdateTimeStepsDeleter(config.max_misses + 1), detector=feed,
                              data_associator=GNNWith2DAssignment(hypothesiser), updater=updater)


def _jpda(config: TrackerConfig, settings: StoneSoupSettings, feed: _Feed) -> Any:
    _, predictor, updater = _components(config, settings)
    hypothesiser = PDAHypothesiser(predictor, updater, clutter_spatial_density=_clutter_density(config, settings),
                                   prob_detect=settings.prob_detect, prob_gate=settings.prob_gate)
    return MultiTargetMixtureTracker(initiator=_initiator(config, predictor, updater),
                                     deleter=UpdateTimeStepsDeleter(config.max_misses + 1), detector=feed,
                                     data_associator=JPDA(hypothesiser), updater=updater)


def _gmphd(config: TrackerConfig, settings: StoneSoupSettings, feed: _Feed) -> Any:
    _, predictor, updater = _components(config, settings)
    gate = float(np.sqrt(config.gate_chi2))
    hypothesiser = GaussianMixtureHypothesiser(
        DistanceHypothesiser(predictor, updater, measure=Mahalanobis(), missed_distance=gate), order_by_detection=True)
    phd_updater = PHDUpdater(updater, clutter_spatial_density=_clutter_density(config, settings),
                             prob_detection=settings.prob_detect, prob_survival=settings.prob_survival)
    speed = config.initial_speed_sigma_mps
    # one broad birth component over the field of view (ranges up to max_range_m in front)
    half = settings.max_range_m / 2
    birth = TaggedWeightedGaussianState(np.array([[0.0], [0.0], [half], [0.0]]),
                                        np.diag([half**2, speed**2, (0.6 * half) ** 2, speed**2]),
                                        weight=settings.birth_weight,
                                        tag=TaggedWeightedGaussianState.BIRTH, timestamp=EPOCH)
    reducer = GaussianMixtureReducer(prune_threshold=settings.prune_threshold,
                                     merge_threshold=settings.merge_threshold)
    return PointProcessMultiTargetTracker(detector=feed, updater=phd_updater, hypothesiser=hypothesiser,
                                          reducer=reducer, birth_component=birth,
                                          extraction_threshold=settings.extraction_threshold)


BUILDERS: dict[str, Callable[[TrackerConfig, StoneSoupSettings, _Feed], Any]] = {
    "gnn": _gnn, "jpda": _jpda, "gmphd": _gmphd}
