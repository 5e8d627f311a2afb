"""The trainer: a few steps of each stage on a tiny store, checkpoints that resume and rebuild alone,
the segmenter's seed jitter, the CLI, and Ray Train with 2 CPU workers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from models.checkpoint import export_checkpoint, load_checkpoint
from pipelines.datasets.store_info import StoreInfo
from pipelines.jobs import parse_config
from pipelines.training import train as train_job
from pipelines.training.config import RECIPES, TrainConfig
from pipelines.training.jitter import SeedJitter
from pipelines.training.loop import Budget, train, train_loop
from pipelines.training.optim import make_optimizer
from pipelines.training.segmenter import RoiDataset, collate_roi


def parse_args(argv):
    return parse_config(train_job, argv, "radarseg train")


def _detector_cfg(store, out, **kw) -> TrainConfig:
    return TrainConfig(stage="detector", store=str(store), out=str(out), model="centre_detector_tiny",
                       model_config={}, batch_size=2, epochs=1, max_steps=2, progress=False, **kw)


def _lines(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_detector_trains_resumes_and_rebuilds(small_store, tmp_path):
    run = tmp_path / "det"
    result = train_loop(_detector_cfg(small_store, run))
    assert result["step"] == 1 and np.isfinite(result["train_total"])  # 3 train frames, batch 2: 1 step/epoch
    assert {"val_mAP", "val_AP@1", "val_loss", "frames_per_second"} <= set(result)
    for name in ("config.json", "metrics.jsonl", "last.pt", "model.pt"):
        assert (run / name).is_file(), name
    assert len(_lines(run / "metrics.jsonl")) == 1

    # the checkpoint alone rebuilds the model: architecture, preset, classes, normalisation
    checkpoint = load_checkpoint(run / "model.pt")
    assert checkpoint.model_name == "centre_detector_tiny" and checkpoint.preset == "small"
    assert checkpoint.class_names[0] == "background" and len(checkpoint.class_names) == 4
    assert {"mean", "std", "mean_per_doppler", "std_per_doppler"} <= set(checkpoint.normalisation)
    assert "optimizer" not in checkpoint.extra  # weights only: what ships
    model = checkpoint.build()
    with torch.no_grad():
        out = model(torch.zeros(1, 32, 128, 128))
    assert out["heatmap"].shape == (1, 1, 32, 32)

    # the shippable copy: float16 weights, no optimiser, same outputs to float16 precision
    shipped = load_checkpoint(export_checkpoint(run / "last.pt", run / "shipped.pt"))
    assert "optimizer" not in shipped.extra and shipped.extra["stored_dtype"] == "float16"
    def weight_bytes(c) -> int:  # noqa: ANN001
        return sum(t.numel() * t.element_size() for t in c.state_dict.values() if t.is_floating_point())

    assert 2 * weight_bytes(shipped) == weight_bytes(checkpoint)  # every floating tensor in half the bytes
    assert (run / "shipped.pt").stat().st_size < 0.65 * (run / "model.pt").stat().st_size  # and the file shrinks
    with torch.no_grad():
        half = shipped.build()(torch.zeros(1, 32, 128, 128))
    assert torch.allclose(half["heatmap"], out["heatmap"], atol=2e-2)

    # a second run into the same directory needs --resume; resuming continues the epochs and steps
    with pytest.raises(FileExistsError, match="--resume"):
        train_loop(_detector_cfg(small_store, run))
    resumed = train_loop(TrainConfig(**{**_detector_cfg(small_store, run).to_dict(), "resume": True, "epochs": 2,
                                        "max_steps": 4}))
    assert resumed["epoch"] == 2 and resumed["step"] == 2
    lines = _lines(run / "metrics.jsonl")
    assert [line["epoch"] for line in lines] == [1, 2]
    # only a strictly better validation score is "best" (a tiny detector's mAP stays 0.0: epoch 1 stays the best)
    assert lines[0]["best"] and lines[1]["best"] == (lines[1]["val_mAP"] > lines[0]["val_mAP"])
    last = load_checkpoint(run / "last.pt")
    assert last.extra["epoch"] == 2 and "optimizer" in last.extra and last.extra["elapsed_s"] > 0
    # resuming with other settings is refused
    other = TrainConfig(**{**_detector_cfg(small_store, run).to_dict(), "resume": True, "lr": 0.5, "epochs": 3})
    with pytest.raises(ValueError, match="lr"):
        train_loop(other)


def test_same_seed_same_weights(small_store, tmp_path):
    a = train_loop(_detector_cfg(small_store, tmp_path / "a", seed=3))
    b = train_loop(_detector_cfg(small_store, tmp_path / "b", seed=3))
    assert a["train_total"] == pytest.approx(b["train_total"], rel=1e-5)
    wa, wb = (load_checkpoint(tmp_path / name / "model.pt").state_dict for name in ("a", "b"))
    assert all(torch.allclose(wa[k].float(), wb[k].float(), atol=1e-5) for k in wa)


@pytest.mark.parametrize("model", ["minkunet_tiny", "spvcnn_tiny"])
def test_segmenter_trains_with_the_same_command(small_store, tmp_path, model):
    run = tmp_path / model
    cfg = TrainConfig(stage="segmenter", store=str(small_store), out=str(run), model=model, model_config={},
                      batch_size=2, epochs=1, max_steps=1, jitter_std=(1.0, 1.0, 0.5), progress=False)
    result = train_loop(cfg)
    assert result["step"] == 1 and np.isfinite(result["train_ce"])
    assert 0.0 <= result["val_mIoU"] <= 1.0 and 0.0 < result["val_roi_recall"] <= 1.0
    weights = json.loads((run / "class_weights.json").read_text())["weights"]
    assert len(weights) == 4 and np.mean(weights) == pytest.approx(1.0, rel=0.2)
    assert weights[0] < max(weights[1:])  # background is the most frequent class in the ROI
    jitter = json.loads((run / "jitter.json").read_text())
    assert jitter["std"] == [1.0, 1.0, 0.5] and jitter["source"].startswith("gaussian")
    checkpoint = load_checkpoint(run / "model.pt")
    assert checkpoint.model_name == model and checkpoint.extra["stage"] == "segmenter"
    checkpoint.build()


def test_lovasz_option_and_learning_curve_points(small_store, tmp_path):
    run = tmp_path / "lovasz"
    cfg = TrainConfig(stage="segmenter", store=str(small_store), out=str(run), model="minkunet_tiny", model_config={},
                      batch_size=2, epochs=2, max_steps=2, jitter_std=(1.0, 1.0, 0.5), progress=False,
                      lovasz_weight=0.5, curve_every=1, val_frames=2)
    result = train_loop(cfg)
    assert 0.0 < result["train_lovasz"] <= 1.0
    assert result["train_total"] == pytest.approx(result["train_ce"] + 0.5 * result["train_lovasz"], rel=1e-6)
    curve = _lines(run / "curve.jsonl")
    assert [p["step"] for p in curve] == [0, 1, 2]  # before the first step, then every step (epoch ends here)
    # training CPU seconds: each point after a step has spent more (validation excluded), whatever the machine's speed
    assert curve[0]["cpu_s"] < curve[1]["cpu_s"] < curve[2]["cpu_s"]
    for point in curve:
        for view in ("RA", "RD"):
            assert 0.0 <= point[f"val_{view}_mIoU"] <= 1.0
            assert {f"val_{view}_iou_pedestrian", f"val_{view}_iou_car"} <= set(point)
    assert curve[-1]["val_RA_mIoU"] == result["val_RA_mIoU"]  # the epoch's validation is the curve's point
    with pytest.raises(ValueError, match="lovasz_weight is a segmenter loss"):
        _detector_cfg(small_store, tmp_path / "det", lovasz_weight=1.0)


def test_roi_samples_and_measured_jitter(small_store):
    store = StoreInfo.read(small_store)
    residuals = np.array([[2.0, -1.0, 0.5], [-2.0, 1.0, -0.5]])
    jitter = SeedJitter(residuals, (0.0, 0.0, 0.0), "measured: test")
    drawn = jitter.sample(50, np.random.default_rng(0))
    assert {tuple(row) for row in drawn} <= {tuple(row) for row in residuals}  # resampled, never invented
    dataset = RoiDataset(store, "train", jitter, seed=1)
    sample = dataset[0]
    n = len(sample["coords"])
    assert n > 0 and sample["features"].shape == (n, 4) and sample["labels"].shape == (n,)
    assert int(sample["labels"].max()) > 0  # the ROI holds object voxels
    again = dataset[0]
    assert torch.equal(sample["coords"], again["coords"])  # reproducible for one epoch
    batch = collate_roi([sample, again])
    assert batch["coords"].shape == (2 * n, 4) and batch["coords"][:, 0].tolist() == [0] * n + [1] * n


def test_profiles_and_arguments(small_store, tmp_path):
    assert RECIPES["detector"]["paper"].lr == 1e-4 and RECIPES["detector"]["paper"].epochs == 300
    assert RECIPES["segmenter"]["paper"].lr == 0.24
    cfg = parse_args(["segmenter", "--store", str(small_store), "--out", str(tmp_path), "--model", "spvcnn",
                      "--model-config", '{"ratio": 0.2}', "--jitter-std", "1", "2", "0.5", "--epochs", "3"])
    hyper = cfg.hyper()
    assert hyper.model == "spvcnn" and hyper.model_config == {"ratio": 0.2} and hyper.epochs == 3
    assert hyper.jitter_std == (1.0, 2.0, 0.5) and hyper.lr == RECIPES["segmenter"]["quick"].lr
    with pytest.raises(ValueError, match="stage"):
        TrainConfig(stage="tracker", store="s", out="o")
    with pytest.raises(ValueError, match="names its model"):
        TrainConfig(stage="baseline", store="s", out="o")
    with pytest.raises(ValueError, match="either jitter_from"):
        TrainConfig(stage="segmenter", store="s", out="o", jitter_from="d.pt", jitter_std=(1, 1, 1))


def test_cli_train(small_store, tmp_path, capsys):
    from pipelines.cli import main as cli

    run = tmp_path / "cli"
    code = cli(["train", "detector", "--store", str(small_store), "--out", str(run), "--model",
                "centre_detector_tiny", "--model-config", "{}", "--batch-size", "2", "--epochs", "1",
                "--max-steps", "1", "--val-split", "none", "--no-progress"])
    assert code == 0 and (run / "model.pt").is_file()
    assert "model.pt" in capsys.readouterr().out


@pytest.mark.ray
@pytest.mark.slow
def test_ray_train_two_workers(small_store, tmp_path):
    run = tmp_path / "ray"
    cfg = TrainConfig(stage="segmenter", store=str(small_store), out=str(run), model="minkunet_tiny",
                      model_config={}, batch_size=1, epochs=2, max_steps=2, jitter_std=(1.0, 1.0, 0.5),
                      val_split=None, ray_workers=2, progress=False)
    result = train(cfg)
    lines = _lines(run / "metrics.jsonl")
    assert [line["epoch"] for line in lines] == [1, 2] and lines[-1]["step"] == 2
    assert lines[-1]["frames_per_second"] > 0 and result["metrics"]["step"] == 2
    load_checkpoint(run / "model.pt").build()


def test_optimizer_override_for_sparsity_training():
    params = [torch.nn.Parameter(torch.ones(3))]
    segmenter = TrainConfig(stage="segmenter", store="s.zarr", out="o")
    assert isinstance(make_optimizer(segmenter.hyper(), params), torch.optim.SGD)
    adam = TrainConfig(stage="segmenter", store="s.zarr", out="o", optimizer="adam")
    assert adam.hyper().optimizer == "adam" and adam.identity()["optimizer"] == "adam"
    assert isinstance(make_optimizer(adam.hyper(), params), torch.optim.Adam)
    detector = TrainConfig(stage="detector", store="s.zarr", out="o", optimizer="sgd")
    assert isinstance(make_optimizer(detector.hyper(), params), torch.optim.SGD)
    with pytest.raises(ValueError, match="optimizer"):
        TrainConfig(stage="segmenter", store="s.zarr", out="o", optimizer="lbfgs")
    assert parse_args(["segmenter", "--store", "s.zarr", "--out", "o", "--optimizer", "adam"]).optimizer == "adam"


def test_budget_counts_steps_minutes_and_time_already_spent():
    assert Budget(2, None).spent(2) and not Budget(2, None).spent(1)
    assert not Budget(None, 10.0).spent(10**6)
    assert Budget(None, 10.0, spent_s=600.0).spent(0)  # a resumed run that had used its 10 minutes
    assert not Budget(None, None).spent(10**6)


def test_empty_validation_split_is_refused_and_leaves_no_run_directory(small_store, tmp_path):
    run = tmp_path / "det"
    with pytest.raises(ValueError, match="--val-split none"):
        train_loop(_detector_cfg(_empty_val_store(small_store, tmp_path), run))
    assert not run.exists()  # a failed command leaves no half-written run directory


def _empty_val_store(small_store, tmp_path):
    """A copy of the tiny store whose validation frames are all marked invalid."""
    import shutil

    import zarr

    copy = tmp_path / "noval.zarr"
    shutil.copytree(small_store, copy)
    root = zarr.open_group(str(copy), mode="r+")
    split, valid = root["split"][:], root["valid"][:]
    valid[split == 1] = 0
    root["valid"][:] = valid
    return copy


def test_another_model_drops_the_profiles_builder_arguments_and_bad_ones_are_named(small_store, tmp_path):
    cfg = TrainConfig(stage="segmenter", store="s.zarr", out="o", model="minkunet_tiny")
    assert cfg.hyper().model_config == {}  # the quick recipe's {"ratio": 0.25} is MinkUNet's, not the tiny variant's
    assert TrainConfig(stage="segmenter", store="s.zarr", out="o").hyper().model_config == {"ratio": 0.25}
    bad = TrainConfig(stage="detector", store=str(small_store), out=str(tmp_path / "bad"),
                      model="centre_detector_tiny", model_config={"depth": 3}, max_steps=1, progress=False)
    with pytest.raises(ValueError, match="--model-config"):
        train_loop(bad)
    assert not (tmp_path / "bad").exists()
