"""The 2-D baselines trained by the same loop: runs that resume and rebuild, one-view models, budgets."""

from __future__ import annotations

import numpy as np
import pytest

from models.checkpoint import load_checkpoint
from pipelines.datasets.views import ViewDataset, load_baseline
from pipelines.evaluation.scoring import score_baseline
from pipelines.training.config import TrainConfig
from pipelines.training.loop import train_loop


def baseline_config(**kw) -> TrainConfig:
    return TrainConfig(stage="baseline", **kw)


def test_training_job_writes_a_run_that_resumes_and_rebuilds(seq_store, tmp_path):
    out = tmp_path / "tmva"
    cfg = baseline_config(model="tmvanet_tiny", store=str(seq_store), out=str(out), epochs=2, batch_size=2,
                         progress=False)
    metrics = train_loop(cfg)
    assert metrics["epoch"] == 2 and np.isfinite(metrics["train_total"]) and metrics["val_frames"] == 2
    assert {p.name for p in out.iterdir()} >= {"config.json", "metrics.jsonl", "last.pt", "model.pt"}
    assert len((out / "metrics.jsonl").read_text().splitlines()) == 2
    with pytest.raises(FileExistsError):
        train_loop(cfg)
    resumed = train_loop(TrainConfig(**{**cfg.to_dict(), "epochs": 3, "resume": True}))
    assert resumed["epoch"] == 3 and resumed["step"] == 3
    model, checkpoint, stats = load_baseline(out / "model.pt")
    assert checkpoint.extra["n_frames"] == 5 and checkpoint.extra["views"] == ["rd", "ra"]
    assert load_checkpoint(out / "last.pt").extra["epoch"] == 3
    scores = score_baseline(model, ViewDataset(seq_store, "test", n_frames=5, stats=stats), num_classes=4)
    assert scores["frames"] == 2 and 0.0 <= scores["mIoU"] <= 1.0
    assert np.asarray(scores["confusion_ra"]).sum() == 2 * 128 * 128


def test_unet_job_needs_a_view(seq_store, tmp_path):
    with pytest.raises(ValueError, match="one view"):
        baseline_config(model="unet_tiny", store=str(seq_store), out=str(tmp_path))
    with pytest.raises(ValueError, match="takes no view"):
        baseline_config(model="smvanet", store=str(seq_store), out=str(tmp_path), view="ra")
    metrics = train_loop(baseline_config(model="unet_tiny", view="rd", store=str(seq_store), out=str(tmp_path / "u"),
                                            epochs=1, batch_size=2, max_steps=2, val_split=None, progress=False))
    assert metrics["step"] == 2 and "train_coherence" not in metrics and "train_rd_ce" in metrics


def test_time_budget_stops_a_run_after_its_first_step(seq_store, tmp_path):
    cfg = baseline_config(model="unet_tiny", view="ra", store=str(seq_store), out=str(tmp_path / "u"), epochs=3,
                         batch_size=1, max_minutes=1e-6, threads=1, val_split=None, progress=False)
    metrics = train_loop(cfg)
    assert metrics["epoch"] == 1 and metrics["step"] == 1 and metrics["elapsed_s"] > 0
    with pytest.raises(ValueError, match="max_minutes"):
        TrainConfig(**{**cfg.to_dict(), "max_minutes": 0.0})
