"""Tracking evaluation (pipelines/evaluation/tracking.py) on a tiny simulated store: the metrics are there, the
true centres track almost perfectly, frame gaps are stepped over, a store without tracking truth is refused in
one line; the match distances are 2 / 1 m for a preset and shrink with a radar that sees less than 50 m."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zarr

from pipelines.datasets.store import OBJECT_COLUMN, frames_of_split, open_store, store_profile, tracking_truth_problem
from pipelines.evaluation.report import tracking_headline, tracking_lines
from pipelines.evaluation.tracking import VARIANTS, TrackingFrame, TrackingTally, TruthObjects, evaluate_tracking
from radar.profiles import get_profile, load_profile_file
from radar.tracking import Measurements

INDOOR_PROFILE = Path(__file__).resolve().parents[3] / "docs" / "profiles" / "openradar_ti_2tx4rx.toml"  # 6.25 m


def truth_as_objects(table: np.ndarray, profile) -> list[SimpleNamespace]:
    """The table's objects as a network would give them (perfect detection)."""
    col = OBJECT_COLUMN
    return [SimpleNamespace(x=row[col["x"]], y=row[col["y"]], velocity_mps=float(profile.velocity_mps(
        row[col["doppler_bin"]])), class_id=int(row[col["class_id"]]), score=1.0) for row in table]


def tally_of(path, keep=lambda frame_index: True) -> TrackingTally:
    root = open_store(path)
    profile = store_profile(root.attrs.asdict(), path)
    tally = TrackingTally(profile, tracking_truth_problem(root, path))
    sequence_ids, frame_indices = root["sequence_id"][:], root["frame_index"][:]
    for slot in frames_of_split(root, None)[::-1]:  # any order: the tally sorts each sequence's frames
        if keep(int(frame_indices[slot])):
            table = root["objects"][slot][: int(root["n_objects"][slot])]
            tally.add(sequence_ids[slot], frame_indices[slot], table, truth_as_objects(table, profile))
    return tally


def test_true_centres_track_a_tiny_store_almost_perfectly(seq_store):
    tally = tally_of(seq_store)
    section = tally.summary()
    assert section["sequences"] == 3 and section["frames"] == 18 and section["truth_tracks"] > 3
    assert section["match_distance_m"] == 2.0 and section["secondary_distance_m"] == 1.0
    for source in ("predicted", "truth_centres"):
        for variant in VARIANTS:
            for key in ("match_2m", "match_1m"):
                scores = section[source][variant][key]
                assert set(scores["per_class"]) == {"pedestrian", "cyclist", "car"}
                assert {"mota", "motp", "idf1", "num_switches", "mostly_tracked", "mostly_lost"} <= set(
                    scores["overall"])
        assert section[source]["tracker_ms_per_frame"]["frames"] == 18
        assert set(section[source]["velocity"]["per_class"]) == {"pedestrian", "cyclist", "car"}
    overall = section["truth_centres"]["all_objects"]["match_2m"]["overall"]
    assert overall["mota"] >= 0.9 and overall["motp"] == 0.0 and overall["num_false_positives"] == 0
    assert section["predicted"]["all_objects"] == section["truth_centres"]["all_objects"]  # the same objects
    confirmed = section["truth_centres"]["confirmed"]["match_2m"]["overall"]
    assert confirmed["num_misses"] > 0  # the first frame of every track is tentative
    velocity = section["truth_centres"]["velocity"]["overall"]
    assert velocity["n"] > 0 and velocity["vx_rmse_mps"] < 3.0
    lines = "\n".join(tracking_lines(section))
    assert "## Tracking" in lines and "true centres" in lines and "Tracker time per frame" in lines
    assert tracking_headline(section).startswith("tracking (2 m; all objects / confirmed)")


def test_frames_left_out_are_stepped_over(seq_store):
    section = tally_of(seq_store, keep=lambda i: i % 2 == 0).summary()
    assert section["frames"] == 9
    assert section["truth_centres"]["all_objects"]["match_2m"]["overall"]["mota"] >= 0.8


def test_a_store_from_before_tracking_truth_is_refused_in_one_line(tmp_path):
    root = zarr.open_group(tmp_path / "old.zarr", mode="w")
    root.create_array("objects", shape=(2, 32, 10), dtype="float32", fill_value=float("nan"))
    problem = tracking_truth_problem(root, "old.zarr")
    assert "predates tracking truth" in problem and "preprocess again" in problem and "\n" not in problem
    tally = TrackingTally(SimpleNamespace(), problem)
    tally.add(0, 0, np.zeros((1, 10)), [])  # ignored
    assert tally.summary() == {"skipped": problem} and tally.frames == []
    assert problem in tracking_headline(tally.summary())
    assert problem in "\n".join(tracking_lines(tally.summary()))


def test_objects_without_track_ids_are_no_truth(seq_store):
    root = open_store(seq_store)
    profile = store_profile(root.attrs.asdict(), seq_store)
    table = root["objects"][0][: int(root["n_objects"][0])].copy()
    table[:, OBJECT_COLUMN["track_id"]] = np.nan  # as from a data set without track ids (CARRADA)
    tally = TrackingTally(profile)
    tally.add(0, 0, table, [])
    assert "no track ids" in tally.summary()["skipped"]


def walking_person(offset_m: float) -> list[TrackingFrame]:
    """One person walking away at 1 m/s from 3 m, 8 frames; the network's object ``offset_m`` to its right."""
    frames = []
    for i in range(8):
        y = np.array([3.0 + 0.1 * i])
        truth = TruthObjects(track_id=np.array([7]), class_id=np.array([1]), x=np.zeros(1), y=y, vx=np.zeros(1),
                             vy=np.ones(1), radial_velocity=np.ones(1))
        predicted = Measurements(np.full(1, offset_m), y, np.ones(1), np.ones(1, np.int64), np.ones(1))
        frames.append(TrackingFrame(0, i, truth, predicted))
    return frames


def test_a_preset_matches_within_2_m():
    section = json.loads(json.dumps(evaluate_tracking(walking_person(0.5), get_profile("small"))))  # metrics.json
    assert section["match_distance_m"] == 2.0 and section["secondary_distance_m"] == 1.0
    assert set(section["predicted"]["all_objects"]) == {"match_2m", "match_1m"}
    assert section["predicted"]["all_objects"]["match_2m"]["overall"]["mota"] == 1.0  # 0.5 m off still matches
    assert section["predicted"]["velocity"]["overall"]["n"] > 0
    assert tracking_headline(section).startswith("tracking (2 m; all objects / confirmed)")
    assert "within 2 m" in "\n".join(tracking_lines(section))


def test_a_radar_of_6_m_matches_within_a_scaled_distance():
    profile = load_profile_file(INDOOR_PROFILE)
    assert profile.max_range == pytest.approx(6.25, abs=0.01)
    section = json.loads(json.dumps(evaluate_tracking(walking_person(0.5), profile)))  # as in metrics.json
    match_m, secondary_m = section["match_distance_m"], section["secondary_distance_m"]
    assert match_m == pytest.approx(2.0 * profile.max_range / 50, abs=5e-4) and secondary_m == match_m / 2
    keys = {f"match_{match_m:g}m", f"match_{secondary_m:g}m"}
    assert keys == {"match_0.25m", "match_0.125m"}
    for source in ("predicted", "truth_centres"):
        for variant in VARIANTS:
            assert set(section[source][variant]) == keys
    assert section["truth_centres"]["all_objects"]["match_0.25m"]["overall"]["mota"] == 1.0
    predicted = section["predicted"]["all_objects"]["match_0.25m"]["overall"]
    assert predicted["mota"] < 0 and predicted["num_misses"] == 8  # 0.5 m off is two gates away indoors
    assert section["predicted"]["velocity"]["overall"]["n"] == 0  # the velocity error takes the same distance
    assert tracking_headline(section).startswith("tracking (0.25 m; all objects / confirmed)")
    lines = "\n".join(tracking_lines(section))
    assert "within 0.25 m" in lines and "0.125 m in the last columns" in lines and "MOTA 0.125m" in lines
