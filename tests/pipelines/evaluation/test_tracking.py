"""Tracking evaluation (pipelines/evaluation/tracking.py) on a tiny simulated store: the metrics are there, the
true centres track almost perfectly, frame gaps are stepped over, a store without tracking truth is refused in
one line."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import zarr

from pipelines.datasets.store import OBJECT_COLUMN, frames_of_split, open_store, store_profile, tracking_truth_problem
from pipelines.evaluation.report import tracking_headline, tracking_lines
from pipelines.evaluation.tracking import VARIANTS, TrackingTally


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
