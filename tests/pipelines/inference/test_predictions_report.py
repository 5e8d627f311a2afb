"""Batch segmentation's output can be looked at: `store info` reads a predictions store, and segment-batch
writes a summary and a few pictures beside it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipelines.cli import main as cli
from pipelines.inference.predictions_report import report_dir, summarise_predictions, write_predictions_report
from pipelines.inference.predictions_store import open_predictions
from pipelines.inference.segment_batch import SegmentBatchConfig
from pipelines.inference.segment_batch import main as segment_batch
from tests.conftest import save_tiny_checkpoints


@pytest.fixture(scope="module")
def predictions(small_store, tmp_path_factory):
    made = save_tiny_checkpoints(small_store, tmp_path_factory.mktemp("ckpt"), ("detector", "segmenter"))
    out = tmp_path_factory.mktemp("pred") / "pred.zarr"
    result = segment_batch(SegmentBatchConfig(source=f"store:{small_store}", detector=made["detector"],
                                              segmenter=made["segmenter"], out=str(out), score_threshold=0.0,
                                              max_objects=2, shard_frames=2, progress=False, in_process=True))
    return out, result, made


def test_store_info_reads_a_predictions_store(predictions, capsys):
    out, *_ = predictions
    assert cli(["store", "info", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    group = open_predictions(out)
    valid = group["valid"][:].astype(bool)
    assert summary["kind"] == "predictions" and summary["frames"] == len(valid) == 6
    n_objects = group["n_objects"][:][valid]
    assert summary["detections_per_frame"]["mean"] == pytest.approx(n_objects.mean())
    assert sum(summary["detections_per_frame"]["histogram"].values()) == valid.sum()
    labels = group["labels"][:][valid]
    assert summary["class_voxels"]["background"] == int((labels == 0).sum())
    assert sum(summary["class_voxels"].values()) == labels.size
    assert cli(["store", "info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "detections per frame" in text and "predicted voxels per class" in text


def test_segment_batch_writes_a_summary_and_pictures(predictions):
    out, result, _ = predictions
    folder = report_dir(out)
    assert result["report"] == str(folder) and folder.name == "pred-report"
    assert json.loads((folder / "summary.json").read_text()) == summarise_predictions(out)
    pictures = sorted(folder.glob("frame_*.png"))
    assert 1 <= len(pictures) <= 3 and all(p.stat().st_size > 10_000 for p in pictures)


def test_pictures_show_the_frames_with_most_detections(predictions, tmp_path):
    out, *_ = predictions
    made = write_predictions_report(out, tmp_path / "r", pictures=1)
    n_objects = open_predictions(out)["n_objects"][:]
    assert made["pictures"] == [f"frame_{int(np.argmax(n_objects)):05d}.png"]


def test_progress_counts_frames(small_store, predictions, tmp_path, capsys):
    _, _, made = predictions
    segment_batch(SegmentBatchConfig(source=f"store:{small_store}", detector=made["detector"],
                                     segmenter=made["segmenter"], out=str(tmp_path / "p.zarr"), shard_frames=2,
                                     progress=True, in_process=True))
    err = capsys.readouterr().err
    assert "6/6" in err and "frame" in err  # frames, not shards (3 shards of 2 frames)
