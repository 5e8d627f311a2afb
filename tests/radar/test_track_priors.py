"""Tracks as priors: which centres a track's prediction adds, the tracker's prediction, and the chain in EraseNet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from radar.centres import Centres
from radar.profiles import get_profile
from radar.track_priors import SequenceTracks, TrackPriors, TrackPriorsConfig, centres_with_priors
from radar.tracking import Measurements, Tracker, TrackerConfig, TrackStatus

SMALL = get_profile("small")
REPO = Path(__file__).resolve().parents[2]


def _centres_at(xy_scores: list[tuple[float, float, float]]) -> Centres:
    """Centres at Cartesian points (m) with scores, sorted by descending score as a detector decodes them."""
    rows = sorted(xy_scores, key=lambda row: -row[2])
    x, y, score = (np.array(column, np.float64) for column in zip(*rows, strict=True))
    range_bin, angle_bin = SMALL.bins_from_xy(x, y)
    return Centres(score, range_bin, angle_bin, np.full(len(rows), 16.0))


def _priors(*positions: tuple[float, float], threshold: float = 0.1) -> TrackPriors:
    return TrackPriors(np.array(positions, np.float64).reshape(-1, 2), TrackPriorsConfig(threshold, gate_m=2.0))


def test_a_prediction_without_a_detection_adds_the_best_weak_centre_within_its_gate():
    candidates = _centres_at([(0.0, 20.0, 0.9),   # strong: kept whatever the priors
                              (5.0, 15.0, 0.2),   # weak, 0.5 m from the first prior
                              (5.5, 15.5, 0.15),  # weaker, also in that gate
                              (-8.0, 30.0, 0.25),  # weak, far from every prior
                              (0.5, 20.5, 0.2)])  # weak, but its prior's gate holds the strong centre
    kept, added = centres_with_priors(candidates, 0.3, _priors((5.0, 15.5), (0.0, 20.0), (-3.0, 10.0)), SMALL)
    assert added == 1
    x, y = SMALL.xy(kept.range_bin, kept.angle_bin)
    assert np.allclose(np.c_[x, y], [[0.0, 20.0], [5.0, 15.0]], atol=1e-6)
    assert list(kept.score) == [0.9, 0.2]  # still sorted

    none, added = centres_with_priors(candidates, 0.3, None, SMALL)
    assert added == 0 and list(none.score) == [0.9]


def test_a_centre_stands_for_one_prediction_and_the_lower_score_is_respected():
    candidates = _centres_at([(5.0, 15.0, 0.2), (5.2, 15.0, 0.05)])
    kept, added = centres_with_priors(candidates, 0.3, _priors((4.8, 15.0), (5.4, 15.0), threshold=0.1), SMALL)
    assert added == 1 and list(kept.score) == [0.2]  # the second prediction finds only a centre under 0.1
    kept, added = centres_with_priors(candidates, 0.3, _priors((4.8, 15.0), (5.4, 15.0), threshold=0.04), SMALL)
    assert added == 2 and list(kept.score) == [0.2, 0.05]


@pytest.mark.parametrize("threshold, gate_m", [(0.0, 2.0), (1.0, 2.0), (float("nan"), 2.0), (0.1, 0.0),
                                               (0.1, float("inf"))])
def test_bad_priors_settings_are_refused(threshold, gate_m):
    with pytest.raises(ValueError, match="track priors"):
        TrackPriorsConfig(threshold, gate_m)


def test_confirmed_tracks_predict_their_next_position_and_the_prediction_changes_nothing():
    config = TrackerConfig.for_profile(SMALL)
    dt = config.frame_period_s
    tracker = Tracker(config)
    for k in range(6):  # a car at 10 m/s across the line of sight
        x, y = -10.0 + 10.0 * k * dt, 20.0
        radial = x * 10.0 / np.hypot(x, y)
        tracker.step(Measurements(np.array([x]), np.array([y]), np.array([radial]), np.array([3]), np.ones(1)))
    state = tracker.to_state()
    predicted = tracker.predicted_positions(frames=2)
    assert predicted.shape == (1, 2)
    mean = tracker.tracks[0].mean
    assert predicted[0] == pytest.approx(mean[:2] + 2 * dt * mean[2:])  # the constant-velocity model's prediction
    assert predicted[0] == pytest.approx([-10.0 + 10.0 * 7 * dt, 20.0], abs=0.6)  # near the car's next position
    assert tracker.to_state() == state
    tentative = Tracker(config)
    tentative.step(Measurements(np.array([1.0]), np.array([10.0]), np.zeros(1), np.array([1]), np.ones(1)))
    assert tentative.tracks[0].status is TrackStatus.tentative and tentative.predicted_positions().shape == (0, 2)


def test_sequence_tracks_predict_from_the_second_frame_and_refuse_frames_out_of_order():
    tracks = SequenceTracks(TrackerConfig.for_profile(SMALL), TrackPriorsConfig(0.1))

    class Obj:
        x, y, velocity_mps, class_id, score = 2.0, 15.0, 0.0, 1, 0.9

    assert tracks.priors(7, 0) is None
    tracks.step(7, 0, [Obj()])
    assert len(tracks.priors(7, 1).positions) == 0  # tentative after one frame
    tracks.step(7, 1, [Obj()])
    priors = tracks.priors(7, 3)
    assert priors.positions == pytest.approx(np.array([[2.0, 15.0]]), abs=0.5)
    assert tracks.priors(8, 5) is None  # another sequence has its own tracker
    with pytest.raises(ValueError, match="in order"):
        tracks.priors(7, 1)


def test_erasenet_seeds_from_a_prior_that_the_operating_score_missed_and_the_segmenter_decides():
    from models.erasenet.model import EraseNet
    from radar.input_kind import InputKind

    net = EraseNet.from_checkpoints(REPO / "checkpoints/detector.pt", REPO / "checkpoints/segmenter.pt")
    log_power = _simulated_log_power()
    candidates = net.detect(log_power, score_threshold=0.01)
    best = (float(candidates.range_bin[0]), float(candidates.angle_bin[0]))
    net.score_threshold = 0.999  # nothing passes the operating score: every object must come from a prior
    plain = net.segment(log_power, kind=InputKind.log_power)
    assert len(plain.centres) == 0 and plain.objects == [] and plain.prior_seeds == 0
    prior = _priors(tuple(float(v) for v in SMALL.xy(*best)), threshold=0.01)
    seeded = net.segment(log_power, kind=InputKind.log_power, priors=prior)
    assert seeded.prior_seeds == 1 and len(seeded.centres) == 1
    assert (seeded.centres.range_bin[0], seeded.centres.angle_bin[0]) == pytest.approx(best)
    assert len(seeded.regions) > 0
    assert len(seeded.objects) == int(((seeded.regions.seed_index == 0) & (seeded.labels[
        tuple(seeded.regions.voxels.T)] > 0)).any())  # an object only where the segmenter labels foreground
    with pytest.raises(ValueError, match="no centres"):
        net.segment(log_power, kind=InputKind.log_power, priors=prior, centres=candidates)


def _simulated_log_power() -> np.ndarray:
    from radar.simulate import simulate_sequence

    frame = next(iter(simulate_sequence("small", 1, seed=5)))
    return frame.log_power().astype(np.float32)
