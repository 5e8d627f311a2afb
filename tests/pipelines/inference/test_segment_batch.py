"""The batch segmentation job without Ray: its plan and argument checks, and the job run in-process (predictions
equal ERASE-Net's own, quarantine of bad frames, resume). The Ray paths (job submission to a two-node cluster,
resume) are in tests/deploy/test_topology.py."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from models.erasenet.model import EraseNet
from pipelines.datasets.sharded_store import done_shards
from pipelines.datasets.store import open_store
from pipelines.inference.predictions_store import (
    COMPUTE_FIELDS,
    PREDICTION_OBJECT_FIELDS,
    create_predictions,
    open_predictions,
)
from pipelines.inference.segment_batch import SegmentBatchConfig, format_result, main, plan_job
from pipelines.jobs import run_module
from radar.input_kind import InputKind
from tests.pipelines.conftest import save_tiny_checkpoints


@pytest.fixture(scope="module")
def tiny_checkpoints(small_store, tmp_path_factory):
    """Untrained tiny detector and segmenter for the small preset."""
    made = save_tiny_checkpoints(small_store, tmp_path_factory.mktemp("ckpt"))
    return made["detector"], made["segmenter"]


def _config(source: str, tiny_checkpoints, out, **overrides) -> SegmentBatchConfig:
    det, seg = tiny_checkpoints
    values = {"source": source, "detector": str(det), "segmenter": str(seg), "out": str(out),
              "score_threshold": 0.0, "max_objects": 2, "shard_frames": 2, "progress": False, "in_process": True}
    values.update(overrides)
    return SegmentBatchConfig(**values)


def test_job_in_process_writes_what_erasenet_predicts(small_store, tiny_checkpoints, tmp_path):
    cfg = _config(f"store:{small_store}", tiny_checkpoints, tmp_path / "pred.zarr", split="train")
    result = main(cfg)
    (stage,) = result["worker_stats"]  # one ShardSegmenter in this process: the model loaded once
    assert stage["model_loads"] == 1 and stage["calls"] == stage["shards"] == result["shards"] == result["shards_run"]
    assert result["workers"] == 1 and result["frames_per_second"] > 0
    assert format_result(result).startswith(f"predictions {cfg.out}: 3/3 frames segmented, 0 quarantined, 2 shards")
    summaries = done_shards(cfg.out)
    assert set(summaries) == set(range(result["shards"]))
    source = open_store(small_store)
    train_slots = np.flatnonzero(source["split"][:] == 0)
    root = open_predictions(cfg.out)
    assert root.attrs["report"]["written"] == 3 and root.attrs["code_version"]["package"] == "0.1.0"
    assert root["source_slot"][:].tolist() == train_slots.tolist()
    net = EraseNet.from_checkpoints(cfg.detector, cfg.segmenter, score_threshold=0.0, max_objects=2)
    for k, slot in enumerate(train_slots):
        expected = net.segment(source["input"][slot].astype(np.float32), kind=InputKind.log_power)
        np.testing.assert_array_equal(root["labels"][k], expected.labels)
        np.testing.assert_array_equal(root["ra_mask"][k], expected.ra_mask)
        np.testing.assert_array_equal(root["rd_mask"][k], expected.rd_mask)
        assert root["n_objects"][k] == len(expected.objects)
        for row, obj in zip(root["objects"][k], expected.objects, strict=False):
            np.testing.assert_allclose(row, [getattr(obj, f) for f in PREDICTION_OBJECT_FIELDS], rtol=1e-6)
        compute = dict(zip(COMPUTE_FIELDS, root["compute"][k], strict=True))
        assert compute["macs_total"] == expected.compute.macs_total > 0
        assert compute["roi_voxels"] == expected.compute.roi_voxels
        assert root["frame_index"][k] == source["frame_index"][slot]
    assert result["macs_total"] == int(root["compute"][:, COMPUTE_FIELDS.index("macs_total")].sum())
    assert sum(s["macs"] for s in summaries.values()) == result["macs_total"]
    _check_tracks(cfg.out, net.profile, tmp_path)
    again = main(cfg)  # a rerun of a finished store does no work
    assert (again["shards_run"], again["shards_skipped"], again["written"]) == (0, 2, 3)
    np.testing.assert_array_equal(open_predictions(cfg.out)["tracks"][:], root["tracks"][:])


def _check_tracks(path, profile, tmp_path):
    """``tracks``: the tracker over the frames' object tables in order, one row per object; the report shows it;
    a store without it still opens."""
    import zarr

    from pipelines.inference.batch_tracks import track_sequence
    from pipelines.inference.predictions_report import format_predictions, summarise_predictions
    from radar.tracking import TrackerConfig

    root = open_predictions(path)
    n_objects, tracks = root["n_objects"][:], root["tracks"][:]
    assert tracks.shape == (3, 2, 3) and root.attrs["tracking"]["sequences"] == 1
    expected, _ = track_sequence(root["objects"][:], n_objects, root["frame_index"][:],
                                 TrackerConfig.for_profile(profile))
    np.testing.assert_array_equal(tracks, expected)
    for k, n in enumerate(n_objects):
        assert np.isfinite(tracks[k, :n]).all() and np.isnan(tracks[k, n:]).all()
    assert tracks[0, : n_objects[0], 0].tolist() == list(range(1, n_objects[0] + 1))
    summary = summarise_predictions(path)
    assert summary["tracks"]["objects_tracked"] == summary["tracks"]["objects"] == int(n_objects.sum())
    assert "tracks: " in format_predictions(summary)
    old = tmp_path / "old.zarr"
    shutil.copytree(path, old)
    del zarr.open_group(old, mode="r+")["tracks"]
    summary = summarise_predictions(old)
    assert summary["tracks"] is None and "tracks: none" in format_predictions(summary)


def test_job_on_the_onnx_engine_writes_what_the_torch_engine_predicts(small_store, tiny_checkpoints, tmp_path,
                                                                     monkeypatch):
    monkeypatch.setenv("RADARSEG_ONNX_CACHE", str(tmp_path / "onnx"))
    torch_cfg = _config(f"store:{small_store}", tiny_checkpoints, tmp_path / "torch.zarr", split="val")
    onnx_cfg = _config(f"store:{small_store}", tiny_checkpoints, tmp_path / "onnx.zarr", split="val", runtime="onnx")
    assert main(onnx_cfg)["written"] == main(torch_cfg)["written"] > 0
    assert len(list((tmp_path / "onnx").glob("*/manifest.json"))) == 1  # exported once, before the shards
    torch_root, onnx_root = open_predictions(torch_cfg.out), open_predictions(onnx_cfg.out)
    roi = torch_root["labels"][:] > 0
    assert roi.any() and (onnx_root["labels"][:][roi] == torch_root["labels"][:][roi]).mean() >= 0.999
    np.testing.assert_array_equal(onnx_root["n_objects"][:], torch_root["n_objects"][:])
    macs = COMPUTE_FIELDS.index("macs_total")
    np.testing.assert_array_equal(onnx_root["compute"][:, macs], torch_root["compute"][:, macs])


def test_bad_recording_frames_are_quarantined(small_recording, tiny_checkpoints, tmp_path):
    recording = tmp_path / "rec"
    shutil.copytree(small_recording, recording)
    bad = sorted((recording / "seq_000" / "cubes").glob("*.npy"))[1]
    bad.write_bytes(b"not a numpy file")
    cfg = _config(f"recording:{recording}", tiny_checkpoints, tmp_path / "pred.zarr", limit=4)
    result = main(cfg)
    assert (result["frames"], result["written"], result["quarantined"]) == (4, 3, 1)
    quarantined = open_predictions(cfg.out).attrs["report"]["quarantined"]
    assert [(q["sequence"], q["index"]) for q in quarantined] == [("seq_000", 1)]
    assert bad.name in quarantined[0]["reason"]
    assert open_predictions(cfg.out)["valid"][:].tolist() == [1, 0, 1, 1]


def test_arguments_are_checked_before_any_work(small_store, small_recording, tiny_checkpoints, tmp_path, capsys):
    det, seg = tiny_checkpoints
    base = ["--detector", str(det), "--segmenter", str(seg), "--out", str(tmp_path / "p.zarr")]
    cases = {
        "--source must be": ["--source", "sim", *base],
        "only with a store source": ["--source", f"recording:{small_recording}", "--split", "test", *base],
        "--workers must be >= 1": ["--source", f"store:{small_store}", "--workers", "0", *base],
        "no such checkpoint": ["--source", f"store:{small_store}", *base[:1], str(tmp_path / "none.pt"), *base[2:]],
        "not a zarr store": ["--source", f"store:{tmp_path}", *base],
    }
    for message, argv in cases.items():
        assert run_module("pipelines.inference.segment_batch", argv) == 2  # python -m pipelines.inference.segment_batch
        assert message in capsys.readouterr().err, message
    assert not (tmp_path / "p.zarr").exists()


def test_a_store_of_other_arguments_is_refused(small_store, tiny_checkpoints, tmp_path):
    out = tmp_path / "pred.zarr"
    cfg = _config(f"store:{small_store}", tiny_checkpoints, out, split="train")
    plan = plan_job(cfg)
    create_predictions(plan.out, plan.layout, {"plan": plan.identity(), "job": cfg.to_dict()})
    assert plan_job(cfg).identity() == plan.identity()  # same arguments: resumable
    with pytest.raises(ValueError, match="written with other arguments"):
        plan_job(_config(f"store:{small_store}", tiny_checkpoints, out, split="val"))
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "file").write_text("x")
    with pytest.raises(ValueError, match="not a radarseg predictions store"):
        plan_job(_config(f"store:{small_store}", tiny_checkpoints, tmp_path / "other"))


def test_a_detector_that_reads_history_gets_each_frames_earlier_one_from_stores_and_recordings(
        small_store, small_recording, tmp_path):
    from radar import transforms
    from radar.io.recording import Recording

    made = save_tiny_checkpoints(small_store, tmp_path / "ckpt", ("detector_history", "segmenter"))
    pair = (made["detector_history"], made["segmenter"])
    net = EraseNet.from_checkpoints(*pair, score_threshold=0.0, max_objects=2)
    assert net.history_frames == 1
    # a store: shards of 2 frames, so the third frame's earlier one lies in the shard before
    cfg = _config(f"store:{small_store}", pair, tmp_path / "store-pred.zarr", split="train")
    main(cfg)
    source, root = open_store(small_store), open_predictions(cfg.out)
    for k, slot in enumerate(root["source_slot"][:]):
        history = [None if slot == 0 else source["input"][slot - 1].astype(np.float32)]
        expected = net.segment(source["input"][slot].astype(np.float32), kind=InputKind.log_power, history=history)
        np.testing.assert_array_equal(root["labels"][k], expected.labels)
    # a recording: complex cubes; the earlier frame is read as log power
    cfg = _config(f"recording:{small_recording}", pair, tmp_path / "rec-pred.zarr", limit=3)
    main(cfg)
    recording, root = Recording(small_recording), open_predictions(cfg.out)
    for k in range(3):
        cube = recording.read_frame("seq_000", k).cube
        history = [None if k == 0 else transforms.log_power(recording.read_frame("seq_000", k - 1).cube)]
        np.testing.assert_array_equal(root["labels"][k], net.segment(cube, history=history).labels)
