"""Trackers compared on the same objects (pipelines/evaluation/tracker_comparison.py): ours and Stone Soup's run on a
tiny simulated store's true centres and are scored with GOSPA, HOTA, MOTA / IDF1 and velocity error; HOTA of the
truth itself is 1 and falls with an identity swap; the frames round-trip through their file."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.datasets.store import frames_of_split, open_store, store_profile, tracking_truth_problem
from pipelines.evaluation.tracker_comparison import (
    TRACKERS,
    compare_trackers,
    hota_scores,
    load_frames,
    parse_trackers,
    save_frames,
)
from pipelines.evaluation.tracking import Hypotheses, TrackingFrame, TrackingTally, by_sequence
from radar.profiles import get_profile
from radar.tracking import TrackerConfig
from tests.pipelines.evaluation.test_tracking import truth_as_objects


@pytest.fixture(scope="module")
def truth_frames(seq_store):
    """The tiny store's frames, the network's objects being the true centres (perfect detection)."""
    root = open_store(seq_store)
    profile = store_profile(root.attrs.asdict(), seq_store)
    tally = TrackingTally(profile, tracking_truth_problem(root, seq_store))
    sequence_ids, frame_indices = root["sequence_id"][:], root["frame_index"][:]
    for slot in frames_of_split(root, None):
        table = root["objects"][slot][: int(root["n_objects"][slot])]
        tally.add(sequence_ids[slot], frame_indices[slot], table, truth_as_objects(table, profile))
    return tally.frames, profile


def test_every_tracker_runs_on_the_same_objects_and_is_scored(truth_frames):
    frames, profile = truth_frames
    section = compare_trackers(by_sequence(frames), tuple(TRACKERS), TrackerConfig.for_profile(profile),
                               profile.class_names, 2.0)
    assert section["names"] == list(TRACKERS) and section["gospa"] == {"p": 1.0, "alpha": 2, "c_m": 2.0}
    for name in TRACKERS:
        scores = section[name]
        assert scores["gospa"]["frames"] == len(frames) == 18
        assert len(scores["gospa"]["mean_by_frame_position"]) == 6
        assert 0.0 <= scores["gospa"]["mean_m"] <= 2.0 * 10  # c / 2 per object at most, a few objects a frame
        assert all(0.0 <= scores["hota"][k] <= 1.0 for k in ("hota", "deta", "assa", "loca"))
        assert scores["tracker_ms_per_frame"]["frames"] == 18
    ours = section["radarseg"]
    # true centres: every object found from its second frame on, each keeping its track
    assert ours["mot"]["mota"] > 0.7 and ours["mot"]["num_switches"] <= 1 and ours["hota"]["assa"] > 0.6
    assert ours["gospa"]["mean_by_frame_position"][0] > ours["gospa"]["mean_by_frame_position"][-1]
    assert ours["velocity"]["n"] > 0 and ours["velocity"]["vx_rmse_mps"] < 3.0
    assert section["stonesoup-gnn"]["mot"]["mota"] > 0.5  # the baseline is a working tracker, not a straw man


def truth_as_hypotheses(frames: list[TrackingFrame], swap_after: int | None = None) -> list[Hypotheses]:
    """Every true object reported at its place with its own id; from frame ``swap_after`` on, the first two objects'
    ids exchanged."""
    out = []
    for k, frame in enumerate(frames):
        ids = frame.truth.track_id.copy()
        if swap_after is not None and k >= swap_after and len(ids) >= 2:
            ids[[0, 1]] = ids[[1, 0]]
        n = len(ids)
        out.append(Hypotheses(ids, np.zeros(n, np.int64), np.column_stack([frame.truth.x, frame.truth.y]),
                              np.zeros((n, 2)), np.full(n, 9), np.ones(n, bool)))
    return out


def test_hota_of_the_truth_is_one_and_an_identity_swap_costs_association_only(truth_frames):
    frames, _ = truth_frames
    sequences = by_sequence(frames)
    perfect = hota_scores(sequences, {s: truth_as_hypotheses(g) for s, g in sequences.items()}, 2.0)
    assert perfect == pytest.approx({"hota": 1.0, "deta": 1.0, "assa": 1.0, "loca": 1.0})
    s, group = next((s, g) for s, g in sequences.items() if all(len(f.truth.x) >= 2 for f in g))
    swapped = hota_scores({s: group}, {s: truth_as_hypotheses(group, swap_after=3)}, 2.0)
    assert swapped["deta"] == pytest.approx(1.0) and swapped["assa"] < 0.9 and swapped["hota"] < 0.95


def test_frames_round_trip_through_their_file(truth_frames, tmp_path):
    frames, _ = truth_frames
    loaded = load_frames(save_frames(frames, tmp_path / "frames.npz"))
    assert len(loaded) == len(frames)
    for a, b in zip(frames, loaded, strict=True):
        assert (a.sequence_id, a.frame_index) == (b.sequence_id, b.frame_index)
        np.testing.assert_array_equal(a.truth.track_id, b.truth.track_id)
        np.testing.assert_allclose(a.predicted.radial_velocity, b.predicted.radial_velocity)
        assert b.predicted.class_id.dtype == np.int64
    np.savez(tmp_path / "other.npz", something=np.zeros(2))
    with pytest.raises(ValueError, match="not a file of tracking frames"):
        load_frames(tmp_path / "other.npz")


def test_tracker_names_are_checked():
    assert parse_trackers("radarseg, stonesoup-gnn") == ("radarseg", "stonesoup-gnn")
    with pytest.raises(ValueError, match="stonesoup-gmphd"):
        parse_trackers("radarseg,kalman")


def test_evaluate_compares_trackers_on_the_networks_objects(seq_store, tmp_path):
    from pipelines.evaluation.evaluate import EvaluateConfig, evaluate
    from tests.conftest import save_tiny_checkpoints

    checkpoints = save_tiny_checkpoints(seq_store, tmp_path / "ckpt", ("detector", "segmenter"))
    out = tmp_path / "eval"
    metrics = evaluate(EvaluateConfig(detector=checkpoints["detector"], segmenter=checkpoints["segmenter"],
                                      store=str(seq_store), out=str(out), split=None, pictures=0, sweep_frames=0,
                                      oracle=False, score_threshold=0.05, progress=False,
                                      trackers=("radarseg", "stonesoup-gnn")))
    comparison = metrics["tracking"]["trackers"]
    assert comparison["names"] == ["radarseg", "stonesoup-gnn"]
    assert comparison["radarseg"]["gospa"]["frames"] == comparison["stonesoup-gnn"]["gospa"]["frames"] == 18
    assert (out / "tracking_gospa.png").stat().st_size > 0 and "tracking_gospa.png" in metrics["pictures"]
    assert "### Trackers on the same objects" in (out / "report.md").read_text()
    saved = load_frames(out / "tracking_frames.npz")  # the network's objects, as the trackers got them
    assert len(saved) == 18
    again = compare_trackers(by_sequence(saved), ("radarseg",), TrackerConfig.for_profile(get_profile("small")),
                             ("pedestrian", "cyclist", "car"), 2.0)
    assert again["radarseg"]["gospa"] == comparison["radarseg"]["gospa"]
    with pytest.raises(ValueError, match="trackers must be among"):
        EvaluateConfig(detector="d", segmenter="s", store="x", out="o", trackers=("kalman",))
