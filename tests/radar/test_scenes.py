"""Scenes at the radar's own scale: a profile's [scene] table (indoor rooms), and the metre-valued defaults (region
growing's search grid, AP distance thresholds) that shrink with a radar that sees less than 50 m."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from radar.growing_sweep import DISTANCES_M, search_distances
from radar.metrics import DISTANCE_THRESHOLDS_M, DetectionEvaluator, distance_thresholds_m
from radar.profiles import get_profile
from radar.profiles.files import ProfileError, profile_from_dict, profile_to_dict
from radar.profiles.scene_settings import radar_scale
from radar.simulate import simulate_sequence
from radar.simulate.indoor import IndoorSceneGenerator, indoor_clutter

ROOT = Path(__file__).resolve().parents[2]
TI_PROFILE = ROOT / "docs" / "profiles" / "openradar_ti_2tx4rx.toml"
SCENE = {"range_m": [1.0, 4.5], "classes": {"pedestrian": [1, 2]}, "speed_mps": {"pedestrian": [0.3, 1.4]},
         "min_separation_m": 0.6, "walls": [1, 3], "furniture": [2, 6]}


def indoor_profile(**scene):
    data = tomllib.loads(TI_PROFILE.read_text())
    data["scene"] = {**SCENE, **scene}
    return profile_from_dict(data, source="indoor")


def test_scene_table_reads_and_travels_with_the_profile():
    profile = indoor_profile()
    scene = profile.extra["scene"]
    assert scene.range_m == (1.0, 4.5) and scene.count_range("pedestrian") == (1, 2)
    assert scene.speed_range("pedestrian") == (0.3, 1.4) and scene.walls == (1, 3)
    again = profile_from_dict(profile_to_dict(profile), source="stored")  # checkpoints and stores keep it
    assert again.extra["scene"] == scene


@pytest.mark.parametrize(("scene", "message"), [
    ({"classes": {"car": [1, 1]}}, "does not have"),
    ({"range_m": [1.0, 9.0]}, "beyond the radar"),
    ({"range_m": [0.0, 3.0]}, "above 0 m"),
    ({"walls": [3, 1]}, "min <= max"),
    ({"furniture": [1.5, 2]}, "integers"),
    ({"classes": {"pedestrian": [0, 0]}}, "at least one object"),
    ({"ceiling": 1}, "unknown key"),
])
def test_bad_scene_tables_are_refused_naming_the_key(scene, message):
    with pytest.raises(ProfileError, match=message):
        indoor_profile(**scene)


def test_indoor_scenes_keep_people_in_the_room_and_the_room_static():
    profile = indoor_profile()
    scene = profile.extra["scene"]
    rng = np.random.default_rng(3)
    generator = IndoorSceneGenerator(profile, scene, rng)
    counts, ranges, speeds = set(), [], []
    for _ in range(60):  # six seconds of walking at 10 frames/s
        states = generator.step()
        counts.add(len(states))
        ranges += [s.range_m for s in states]
        speeds += [s.speed for s in states]
    assert counts <= {1, 2} and len(counts) == 1  # people stay in the room: a constant count within the table's
    assert 1.0 - 0.15 <= min(ranges) and max(ranges) <= 4.5 + 0.15  # one step of walking past the edge at most
    assert 0.3 <= min(speeds) and max(speeds) <= 1.4
    clutter = indoor_clutter(profile, scene, np.random.default_rng(4))
    assert np.hypot(clutter.x, clutter.y).max() < profile.max_range  # everything static falls inside the radar


def test_indoor_frames_label_people_at_the_radars_scale():
    profile = indoor_profile()
    frames = list(simulate_sequence(profile, 2, seed=5))
    objects = [o for f in frames for o in f.objects]
    assert objects and all(o.class_name == "pedestrian" and 0.9 < o.true_range_m < 4.7 for o in objects)
    assert all(abs(o.true_velocity_mps) <= 1.4 for o in objects)
    again = list(simulate_sequence(profile, 2, seed=5))
    assert all(np.array_equal(a.cube, b.cube) for a, b in zip(frames, again, strict=True))  # reproducible


def test_built_in_presets_keep_their_metre_defaults():
    for name in ("carrada", "nxp", "small"):
        profile = get_profile(name)
        assert radar_scale(profile) == 1.0
        assert search_distances(profile) == DISTANCES_M
        assert distance_thresholds_m(profile) == DISTANCE_THRESHOLDS_M


def test_a_short_range_radar_gets_its_own_scale():
    profile = get_profile(TI_PROFILE)  # 6.25 m: an eighth of the 50 m radars
    scale = profile.max_range / 50.0
    assert search_distances(profile) == pytest.approx([d * scale for d in DISTANCES_M], abs=1e-4)
    # as many range bins as on the small preset, whose 128 bins also span its whole range
    assert search_distances(profile)[0] / profile.range_res == pytest.approx(
        DISTANCES_M[0] / get_profile("small").range_res, rel=1e-3)
    assert distance_thresholds_m(profile) == pytest.approx([k * scale for k in DISTANCE_THRESHOLDS_M])


def test_scaled_ap_matches_in_metres_of_the_radar_and_doppler_bins_of_the_paper():
    profile = get_profile(TI_PROFILE)
    evaluator = DetectionEvaluator.for_profile(profile)
    # a prediction 0.5 m from the truth, 2 Doppler bins off: within the third level (0.62 m, 5 bins) only
    evaluator.add(np.array([[0.5, 2.0]]), np.array([66.0]), np.array([0.9]), np.array([[0.0, 2.0]]),
                  np.array([64.0]))
    summary = evaluator.summary()
    assert (summary["AP@1"], summary["AP@3"], summary["AP@5"]) == (0.0, 0.0, 1.0)
    assert "within 0.125/0.375/0.625 m and 1/3/5 Doppler bins" in evaluator.thresholds_note()
    paper = DetectionEvaluator()  # at the paper's 1/3/5 m the same prediction matches from the first level
    paper.add(np.array([[0.5, 2.0]]), np.array([66.0]), np.array([0.9]), np.array([[0.0, 2.0]]), np.array([64.0]))
    assert paper.summary()["AP@3"] == 1.0 and paper.summary()["AP@1"] == 0.0
