"""The tracker core (radar/tracking.py): identities through crossings and gaps, track life cycle, class vote,
state round trip, Doppler wrap, refused configurations."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radar.profiles import get_profile
from radar.tracking import Measurements, Tracker, TrackerConfig, TrackStatus

SMALL = get_profile("small")
CONFIG = TrackerConfig.for_profile(SMALL)


def objects(rows: list[tuple[float, float, float, float]], class_id: int = 3, score: float = 1.0) -> Measurements:
    """Measurements of point objects at (x, y) moving at (vx, vy): radial velocity exact."""
    a = np.asarray(rows, np.float64).reshape(-1, 4)
    radial = (a[:, 0] * a[:, 2] + a[:, 1] * a[:, 3]) / np.hypot(a[:, 0], a[:, 1])
    n = len(a)
    return Measurements(a[:, 0], a[:, 1], radial, np.full(n, class_id), np.full(n, score))


def moving(x: float, y: float, vx: float, vy: float, t: float) -> tuple[float, float, float, float]:
    return x + vx * t, y + vy * t, vx, vy


def test_crossing_objects_keep_their_ids():
    tracker = Tracker(CONFIG)
    dt = CONFIG.frame_period_s
    seen: dict[int, set[int]] = {0: set(), 1: set()}
    for k in range(30):  # they cross at frame 15, 2 m apart in y
        step = tracker.step(objects([moving(-7.5, 20.0, 5.0, 0.0, k * dt), moving(7.5, 22.0, -5.0, 0.0, k * dt)]))
        for i in (0, 1):
            seen[i].add(int(step.track_ids[i]))
    assert seen == {0: {1}, 1: {2}}
    vx = {t.id: t.mean[2] for t in step.tracks}
    assert vx[1] == pytest.approx(5.0, abs=0.3) and vx[2] == pytest.approx(-5.0, abs=0.3)


def test_a_gap_is_coasted_and_the_track_continues():
    tracker = Tracker(CONFIG)
    dt = CONFIG.frame_period_s
    for k in range(5):
        step = tracker.step(objects([moving(0.0, 15.0, 2.0, 1.0, k * dt)]))
    assert step.tracks[0].status is TrackStatus.confirmed
    step = tracker.step(Measurements.empty())  # one frame without the object: coasted
    assert [t.status for t in step.tracks] == [TrackStatus.lost] and len(step.confirmed) == 1
    step = tracker.step(objects([moving(0.0, 15.0, 2.0, 1.0, 6 * dt)]))
    assert step.track_ids.tolist() == [1] and step.tracks[0].status is TrackStatus.confirmed
    # frames not seen at all (a gap of frame indices): one step of frames=3
    step = tracker.step(objects([moving(0.0, 15.0, 2.0, 1.0, 9 * dt)]), frames=3)
    assert step.track_ids.tolist() == [1] and step.tracks[0].age == 10 and step.tracks[0].hits == 7
    assert step.tracks[0].mean[:2] == pytest.approx([1.8, 15.9], abs=0.1)


def test_a_tentative_track_survives_frames_not_seen_but_not_a_frame_seen_without_it():
    tracker = Tracker(CONFIG)
    tracker.step(objects([(2.0, 12.0, 1.0, 1.0)]))
    step = tracker.step(objects([moving(2.0, 12.0, 1.0, 1.0, 2 * CONFIG.frame_period_s)]), frames=2)
    assert step.track_ids.tolist() == [1] and step.tracks[0].status is TrackStatus.confirmed
    tracker = Tracker(CONFIG)
    tracker.step(objects([(2.0, 12.0, 1.0, 1.0)]))
    assert tracker.step(Measurements.empty(), frames=CONFIG.max_misses + 2).tracks == []  # too long a gap


def test_a_lost_track_is_dropped_after_max_misses_and_a_tentative_one_sooner():
    tracker = Tracker(CONFIG)
    for _ in range(3):
        tracker.step(objects([(0.0, 10.0, 0.0, 0.0)]))
    for miss in range(1, CONFIG.max_misses + 1):
        step = tracker.step(Measurements.empty())
        assert len(step.tracks) == 1 and step.tracks[0].misses == miss
    assert tracker.step(Measurements.empty()).tracks == []
    tracker.step(objects([(5.0, 10.0, 0.0, 0.0)]))  # tentative (one hit): gone after tentative_max_misses
    for _ in range(CONFIG.tentative_max_misses):
        assert tracker.step(Measurements.empty()).tracks[0].status is TrackStatus.tentative
    assert tracker.step(Measurements.empty()).tracks == []
    assert tracker.step(objects([(5.0, 10.0, 0.0, 0.0)])).track_ids.tolist() == [3]  # ids are never reused


def test_class_is_the_score_weighted_vote():
    tracker = Tracker(CONFIG)
    tracker.step(objects([(0.0, 10.0, 0.0, 0.0)], class_id=1, score=0.3))
    tracker.step(objects([(0.0, 10.0, 0.0, 0.0)], class_id=1, score=0.3))
    step = tracker.step(objects([(0.0, 10.0, 0.0, 0.0)], class_id=3, score=0.5))
    assert step.tracks[0].class_id == 1  # 0.6 against 0.5
    step = tracker.step(objects([(0.0, 10.0, 0.0, 0.0)], class_id=3, score=0.2))
    summary = step.tracks[0].summary()
    assert summary["class_id"] == 3 and summary["hits"] == 4 and summary["status"] == "confirmed"


def test_state_round_trip_gives_identical_next_steps():
    rng = np.random.default_rng(0)
    tracker = Tracker(CONFIG)
    dt = CONFIG.frame_period_s
    truth = [(-5.0, 20.0, 3.0, -1.0), (8.0, 30.0, -2.0, 4.0), (2.0, 8.0, 0.5, 0.5)]
    frames = [objects([moving(*o, k * dt) for o in truth[: 1 + k % 3]]) for k in range(12)]
    frames = [Measurements(m.x + rng.normal(0, 0.2, len(m)), m.y, m.radial_velocity, m.class_id, m.score)
              for m in frames]
    for m in frames[:6]:
        tracker.step(m)
    state = json.loads(json.dumps(tracker.to_state()))
    copy = Tracker.from_state(CONFIG, state)
    assert len(json.dumps(state)) < 600 * max(len(state["tracks"]), 1)
    for m in frames[6:]:
        a, b = tracker.step(m), copy.step(m)
        assert a.track_ids.tolist() == b.track_ids.tolist()
        assert [t.to_state() for t in a.tracks] == [t.to_state() for t in b.tracks]
    with pytest.raises(ValueError, match="version"):
        Tracker.from_state(CONFIG, {**state, "version": 0})


def test_an_aliased_doppler_stays_on_its_track():
    tracker = Tracker(CONFIG)
    vmax = CONFIG.max_radial_velocity_mps
    dt = CONFIG.frame_period_s
    speed = vmax - 0.15  # receding just below the unambiguous limit: noise pushes it over, and it wraps
    for k in range(20):
        y = 10.0 + speed * k * dt
        radial = speed + (0.3 if k % 2 else -0.2)
        wrapped = (radial + vmax) % (2 * vmax) - vmax
        step = tracker.step(Measurements(np.array([0.5]), np.array([y]), np.array([wrapped]), np.array([3]),
                                         np.array([1.0])))
        assert step.track_ids.tolist() == [1], k
    assert step.tracks[0].mean[3] == pytest.approx(speed, abs=0.5)


BAD_CONFIGS = [{"frame_period_s": 0.0}, {"gate_chi2": float("nan")}, {"gate_m": -1.0}, {"confirm_hits": 0},
               {"max_misses": -1}, {"confirm_hits": 2.5}, {"tentative_max_misses": -1},
               {"class_speed_sigma_mps": (1.0, 0.0)}, {"acceleration_sigma_mps2": "2"}]


@pytest.mark.parametrize("override", BAD_CONFIGS)
def test_bad_config_values_are_refused(override):
    with pytest.raises(ValueError):
        TrackerConfig.for_profile(SMALL, **override)


def test_bad_steps_and_measurements_are_refused():
    with pytest.raises(ValueError, match="frames"):
        Tracker(CONFIG).step(Measurements.empty(), frames=0)
    with pytest.raises(ValueError, match="finite"):
        Measurements(np.array([np.nan]), np.array([1.0]), np.array([0.0]), np.array([1]), np.array([1.0]))
    with pytest.raises(ValueError, match="length"):
        Measurements(np.zeros(2), np.zeros(1), np.zeros(1), np.zeros(1, np.int64), np.zeros(1))


def test_a_profile_file_states_the_trackers_settings(tmp_path):
    """[tracking] in a profile file: read, checked, carried in the file form, applied by for_profile; every key it
    takes is a TrackerConfig field."""
    from dataclasses import fields

    from radar.profiles.files import TRACKING_KEYS, ProfileError, profile_from_dict, profile_to_dict

    assert set(TRACKING_KEYS) <= {f.name for f in fields(TrackerConfig)}
    described = profile_to_dict(profile_from_dict(_small_file_form()))
    described["tracking"] = {"gate_m": 6.0, "max_misses": 5}
    profile = profile_from_dict(described)
    config = TrackerConfig.for_profile(profile)
    assert (config.gate_m, config.max_misses) == (6.0, 5)
    assert config.frame_period_s == profile.frame_period_s  # the radar's, whatever the file says
    assert TrackerConfig.for_profile(profile, gate_m=3.0).gate_m == 3.0
    assert profile_from_dict(profile_to_dict(profile)).tracking == profile.tracking
    assert get_profile("small").tracking == ()  # the presets derive theirs
    for bad, message in (({"gate_m": -1.0}, "gate_m"), ({"max_misses": 1.5}, "max_misses"),
                         ({"frame_period_s": 0.2}, "unknown key")):
        with pytest.raises(ProfileError, match=message):
            profile_from_dict({**described, "tracking": bad})


def _small_file_form() -> dict:
    import tomllib
    from pathlib import Path

    import radar.profiles

    return tomllib.loads((Path(radar.profiles.__file__).parent / "presets" / "small.toml").read_text())
