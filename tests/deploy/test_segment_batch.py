"""The batch segmentation job without Ray: its plan and argument checks, and the segmenter stage run in this
process (predictions equal ERASE-Net's own, quarantine of bad frames). The Ray paths (job submission to a
two-node cluster, resume) are in test_topology.py."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from models.erasenet import EraseNet
from pipelines.segment_batch import (
    COMPUTE_FIELDS,
    PREDICTION_OBJECT_FIELDS,
    SegmentBatchConfig,
    ShardSegmenter,
    create_predictions,
    parse_args,
    plan_job,
)
from pipelines.store import done_shards, open_store


def _config(source: str, tiny_checkpoints, out, **overrides) -> SegmentBatchConfig:
    det, seg = tiny_checkpoints
    values = {"source": source, "detector": str(det), "segmenter": str(seg), "out": str(out),
              "score_threshold": 0.0, "max_objects": 2, "shard_frames": 2, "progress": False}
    values.update(overrides)
    return SegmentBatchConfig(**values)


def _run_inline(cfg: SegmentBatchConfig):
    """Every shard through one in-process ShardSegmenter (what each Ray actor does)."""
    from pipelines.segment_batch import ShardJob

    plan = plan_job(cfg)
    create_predictions(plan.out, plan.layout, {"plan": plan.identity(), "job": cfg.to_dict()})
    stage = ShardSegmenter(cfg.detector, cfg.segmenter, score_threshold=cfg.score_threshold,
                           max_objects=cfg.max_objects)
    summaries = [stage(ShardJob(str(plan.out), plan.layout, plan.source, shard, plan.shard_frames(shard)))
                 for shard in range(plan.layout.n_shards)]
    return plan, stage, summaries


def test_segmenter_stage_writes_what_erasenet_predicts(small_store, tiny_checkpoints, tmp_path):
    import zarr

    cfg = _config(f"store:{small_store}", tiny_checkpoints, tmp_path / "pred.zarr", split="train")
    plan, stage, summaries = _run_inline(cfg)
    assert stage.model_loads == 1 and stage.calls == plan.layout.n_shards == len(summaries)
    assert set(done_shards(plan.out)) == set(range(plan.layout.n_shards))
    source = open_store(small_store)
    train_slots = np.flatnonzero(source["split"][:] == 0)
    root = zarr.open_group(str(plan.out), mode="r")
    assert root["source_slot"][:].tolist() == train_slots.tolist()
    net = EraseNet.from_checkpoints(cfg.detector, cfg.segmenter, score_threshold=0.0, max_objects=2)
    for k, slot in enumerate(train_slots):
        expected = net.segment(source["input"][slot].astype(np.float32), is_log_power=True)
        np.testing.assert_array_equal(root["labels"][k], expected.labels)
        np.testing.assert_array_equal(root["ra_mask"][k], expected.ra_mask)
        np.testing.assert_array_equal(root["rd_mask"][k], expected.rd_mask)
        assert root["n_objects"][k] == len(expected.objects)
        for row, obj in zip(root["objects"][k], expected.objects, strict=False):
            np.testing.assert_allclose(row, [getattr(obj, f) for f in PREDICTION_OBJECT_FIELDS], rtol=1e-6)
        compute = dict(zip(COMPUTE_FIELDS, root["compute"][k], strict=True))
        assert compute["macs_total"] == expected.compute["macs"]["total"] > 0
        assert compute["roi_voxels"] == expected.compute["roi_voxels"]
        assert root["frame_index"][k] == source["frame_index"][slot]
    assert sum(s["macs"] for s in summaries) == int(root["compute"][:, COMPUTE_FIELDS.index("macs_total")].sum())


def test_bad_recording_frames_are_quarantined(small_recording, tiny_checkpoints, tmp_path):
    recording = tmp_path / "rec"
    shutil.copytree(small_recording, recording)
    bad = sorted((recording / "seq_000" / "cubes").glob("*.npy"))[1]
    bad.write_bytes(b"not a numpy file")
    cfg = _config(f"recording:{recording}", tiny_checkpoints, tmp_path / "pred.zarr", limit=4)
    plan, _, summaries = _run_inline(cfg)
    assert plan.layout.n_frames == 4
    quarantined = [q for s in summaries for q in s["quarantined"]]
    assert [(q["sequence"], q["index"]) for q in quarantined] == [("seq_000", 1)]
    assert bad.name in quarantined[0]["reason"]
    assert sum(s["written"] for s in summaries) == 3


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
        with pytest.raises(SystemExit) as exit_info:
            parse_args(argv)
        assert exit_info.value.code == 2
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
