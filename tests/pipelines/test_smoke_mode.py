"""RADARSEG_SMOKE=1: a job's command runs as written on tiny sizes (what the README-command test relies on)."""

from __future__ import annotations

from pipelines.datasets.preprocess import PreprocessConfig
from pipelines.jobs import smoke_config
from pipelines.training.config import TrainConfig


def test_smoke_caps_sizes_and_fills_unset_budgets():
    pre = smoke_config(PreprocessConfig(source="sim", out="x.zarr", sequences=1000, frames=3, shard_frames=8))
    assert (pre.sequences, pre.frames, pre.shard_frames, pre.in_process) == (4, 3, 2, True)
    assert smoke_config(PreprocessConfig(source="sim", out="x.zarr")).sequences is None  # the job's default (2)
    train = smoke_config(TrainConfig(stage="detector", store="s.zarr", out="runs/det"))
    assert (train.epochs, train.max_steps, train.batch_size, train.threads) == (1, 2, 2, 1)
    assert smoke_config(TrainConfig(stage="detector", store="s.zarr", out="r", epochs=1, max_steps=1)).max_steps == 1


def test_smoke_mode_is_read_from_the_environment(monkeypatch, small_store, tmp_path):
    from pipelines.jobs import run_job

    monkeypatch.setenv("RADARSEG_SMOKE", "1")
    result, _ = run_job("pipelines.datasets.preprocess", ["--source", "sim", "--sequences", "50", "--frames", "9",
                                                 "--out", str(tmp_path / "s.zarr"), "--no-progress"], prog="t")
    assert result["frames"] == 4 * 6


def test_each_config_declares_its_smoke_rules_beside_the_fields_they_set():
    import dataclasses

    from pipelines.datasets.preprocess import PreprocessConfig as Preprocess
    from pipelines.evaluation.compare import CompareConfig
    from pipelines.evaluation.evaluate import EvaluateConfig
    from pipelines.inference.segment_batch import SegmentBatchConfig
    from pipelines.jobs import SMOKE
    from pipelines.training.slim_sweep import SweepConfig
    from pipelines.training.train import ClassGainsConfig, ClassOffsetsConfig, ExportConfig

    ruled = {Preprocess: {"sequences", "frames", "shard_frames", "in_process"},
             SegmentBatchConfig: {"limit", "shard_frames", "in_process"},
             TrainConfig: {"epochs", "max_steps", "batch_size", "threads", "jitter_from"},
             ClassGainsConfig: {"frames"}, ClassOffsetsConfig: {"max_frames", "threads"}, ExportConfig: set(),
             EvaluateConfig: {"max_frames", "pictures", "sweep_frames", "threads"},
             CompareConfig: {"max_frames", "pictures", "threads"},
             SweepConfig: {"ratios", "max_frames", "finetune_steps", "finetune_steps_baseline", "batch_size",
                           "threads"}}
    for config, names in ruled.items():
        assert {f.name for f in dataclasses.fields(config) if SMOKE in f.metadata} == names, config.__name__
    sweep = smoke_config(SweepConfig(store="s.zarr", finetune_steps=50, threads=4))
    assert (sweep.ratios, sweep.finetune_steps, sweep.threads, sweep.max_frames) == ((0.1,), 1, 1, 2)
    assert sweep.batch_size == 2
