"""The side-by-side comparison: the RA/RD consistency metric, a run of every kind of model on the same
frames of a tiny store (untrained tiny networks: the wiring, not the figures), and its input errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from models.checkpoint import load_checkpoint, save_checkpoint
from pipelines.datasets.store import open_store
from pipelines.datasets.views import ViewDataset, load_baseline
from pipelines.evaluation import compare as compare_job
from pipelines.evaluation.compare import CompareConfig, ModelSpec, compare, parse_model
from pipelines.evaluation.scoring import score_baseline
from pipelines.jobs import parse_config
from radar import transforms
from radar.input_kind import InputKind
from radar.metrics import consistency, consistency_counts
from tests.pipelines.conftest import build_store_inline, save_tiny_checkpoints


@pytest.fixture(scope="module")
def seq_store(tmp_path_factory):
    """small preset, 2 sequences x 6 frames (train, test), built without Ray: TMVA-Net can score 2 test frames."""
    from pipelines.datasets.preprocess import PreprocessConfig

    out = tmp_path_factory.mktemp("compare") / "seq.zarr"
    return build_store_inline(PreprocessConfig(source="sim", out=str(out), preset="small", sequences=2, frames=6,
                                               seed=3, split_fractions=(0.5, 0.0, 0.5), shard_frames=6,
                                               progress=False))


@pytest.fixture(scope="module")
def checkpoints(seq_store, tmp_path_factory):
    return save_tiny_checkpoints(seq_store, tmp_path_factory.mktemp("ckpt"))


def test_consistency_of_hand_built_masks():
    ra = np.zeros((6, 4), np.uint8)
    rd = np.zeros((6, 5), np.uint8)
    ra[1, 2], rd[1, 0] = 3, 3  # a car at range 1 in both views
    ra[4, 0:2], rd[4, 3] = 1, 1  # a pedestrian at range 4 in both
    assert consistency_counts(ra, rd, 4) == (0, 2)
    assert consistency(*consistency_counts(ra, rd, 4)) == 1.0
    ra[2, 1] = 2  # a cyclist at range 2 in RA only: 1 of 3 (range, class) pairs disagrees
    rd[4, 0] = 3  # a car at range 4 in RD only: 2 of 4
    assert consistency_counts(ra, rd, 4) == (2, 4)
    assert consistency(*consistency_counts(ra, rd, 4)) == pytest.approx(0.5)
    assert np.isnan(consistency(*consistency_counts(np.zeros_like(ra), np.zeros_like(rd), 4)))


def test_projections_of_one_labelling_agree():
    """The RA and RD projections of one RAD labelling: occupancy always consistent; per class when each
    range bin holds one class, not always when classes share a range bin (the majority vote drops one)."""
    rng = np.random.default_rng(0)
    labels = np.zeros((16, 8, 6), np.uint8)
    for r in range(16):
        labels[r][rng.random((8, 6)) < 0.2] = rng.integers(1, 4)
    ra, rd = transforms.project_ra(labels, 4), transforms.project_rd(labels, 4)
    assert consistency_counts(ra, rd, 4) == (0, 16)
    mixed = rng.integers(0, 4, size=(16, 8, 6)).astype(np.uint8)
    ra, rd = transforms.project_ra(mixed, 4), transforms.project_rd(mixed, 4)
    assert consistency_counts(ra > 0, rd > 0, 2) == (0, 16)
    # range 0: a car column (a=0) with one pedestrian voxel; RA keeps only the car, RD (d=5) only the pedestrian
    labels = np.zeros((1, 2, 6), np.uint8)
    labels[0, 0, :5], labels[0, 0, 5] = 3, 1
    assert consistency_counts(transforms.project_ra(labels, 4), transforms.project_rd(labels, 4), 4) == (1, 2)


def test_compare_scores_every_model_on_the_same_frames(seq_store, checkpoints, tmp_path):
    c = checkpoints
    models = (ModelSpec("ERASE-Net (tiny)", "erasenet", (c["detector"], c["segmenter"])),
              ModelSpec("CFAR + segmenter", "cfar", (c["segmenter"],)),
              ModelSpec("U-Net", "baseline", (c["unet_ra"], c["unet_rd"])),  # either order
              ModelSpec("TMVA-Net", "baseline", (c["tmvanet"],)),
              ModelSpec("SMVA-Net", "baseline", (c["smvanet"],)))
    out = tmp_path / "cmp"
    result = compare(CompareConfig(store=str(seq_store), out=str(out), models=models, pictures=1,
                                   score_threshold=0.05, progress=False, command="radarseg compare ..."))
    saved = json.loads((out / "compare.json").read_text())
    assert saved["frames"] == result["frames"] == 2 and saved["window"] == 5  # 6 test frames, TMVA needs 4 before
    rows = {row["name"]: row for row in saved["models"]}
    assert [row["frames_scored"] for row in saved["models"]] == [2] * 5
    assert rows["SMVA-Net"]["frames_usable_alone"] == 6 and rows["TMVA-Net"]["frames_usable_alone"] == 2
    for row in saved["models"]:
        for view, width in (("RA", 128), ("RD", 32)):
            assert np.asarray(row[view]["confusion"]).sum() == 2 * 128 * width, (row["name"], view)
        assert row["params"] > 0 and row["seconds_per_frame"] > 0
        assert row["macs_paper"] >= row["macs"] > 0
    # ERASE-Net's views are projections of one labelling: an object at range r in one view is in the other
    for name in ("ERASE-Net (tiny)", "CFAR + segmenter"):
        assert rows[name]["present"] > 0 and rows[name]["occupancy_consistency"] == 1.0
        assert 0.0 <= rows[name]["consistency"] <= 1.0  # per class: mixed labels can be outvoted in one view
    assert saved["truth_occupancy_consistency"] == 1.0
    assert rows["TMVA-Net"]["macs_paper"] > rows["TMVA-Net"]["macs"]  # transposed convs, overcounted
    # the same figures as the baselines' own scoring on the same frames
    model, _, stats = load_baseline(c["tmvanet"])
    own = score_baseline(model, ViewDataset(seq_store, "test", n_frames=5, stats=stats), num_classes=4)
    assert rows["TMVA-Net"]["RD"]["mIoU"] == pytest.approx(own["mIoU_rd"])
    assert rows["TMVA-Net"]["RA"]["mIoU"] == pytest.approx(own["mIoU_ra"])
    model, _, stats = load_baseline(c["smvanet"])
    targets = ViewDataset(seq_store, "test", n_frames=5, stats=stats).windows[:, -1]
    own = score_baseline(model, ViewDataset(seq_store, "test", stats=stats, targets=targets), num_classes=4)
    assert own["frames"] == 2 and rows["SMVA-Net"]["RA"]["mIoU"] == pytest.approx(own["mIoU_ra"])
    report = (out / "compare.md").read_text()
    assert "| U-Net |" in report and "RD mIoU" in report and "2 frames, the same for every model" in report
    assert (out / "compare_frames.png").stat().st_size > 10_000


def test_model_arguments_and_bad_inputs(seq_store, checkpoints, tmp_path):
    c = checkpoints
    assert parse_model("U-Net=a.pt, b.pt", "baseline") == ModelSpec("U-Net", "baseline", ("a.pt", "b.pt"))
    assert parse_model("seg.pt", "cfar", default_name="CFAR").name == "CFAR"
    for text, message in (("tmva.pt", "NAME=CHECKPOINT"), ("=tmva.pt", "model name"), ("X=a.pt,", "checkpoint paths")):
        with pytest.raises(ValueError, match=message):
            parse_model(text, "baseline")
    with pytest.raises(ValueError, match="takes 2 checkpoint"):
        parse_model("E=det.pt", "erasenet")
    cfg = parse_config(compare_job, ["--store", "S", "--out", "O", "--erasenet", "E (M)=d.pt,s.pt", "--baseline",
                                     "T=t.pt", "--cfar-segmenter", "s.pt"], prog="radarseg compare")
    assert [m.kind for m in cfg.models] == ["erasenet", "baseline", "cfar"]
    assert cfg.command.startswith("radarseg compare --store S") and "'E (M)=d.pt,s.pt'" in cfg.command

    def run(*models: ModelSpec, split: str = "test") -> None:
        compare(CompareConfig(store=str(seq_store), out=str(tmp_path / "x"), models=models, split=split,
                              pictures=0, progress=False))

    with pytest.raises(ValueError, match="expected a detector checkpoint"):
        run(ModelSpec("E", "erasenet", (c["segmenter"], c["segmenter"])))
    with pytest.raises(ValueError, match="not a baseline checkpoint"):
        run(ModelSpec("B", "baseline", (c["detector"],)))
    with pytest.raises(ValueError, match="U-Net pair"):
        run(ModelSpec("U-Net", "baseline", (c["unet_ra"],)))
    with pytest.raises(ValueError, match="U-Net pair"):
        run(ModelSpec("U-Net", "baseline", (c["unet_ra"], c["unet_ra"])))
    other = load_checkpoint(c["smvanet"])
    other.preset = "carrada"
    with pytest.raises(ValueError, match="preset 'carrada'.*'small'"):
        run(ModelSpec("S", "baseline", (str(save_checkpoint(other, tmp_path / "carrada.pt")),)))
    with pytest.raises(ValueError, match="nothing to score"):
        run(ModelSpec("S", "baseline", (c["smvanet"],)), split="val")
    with pytest.raises(ValueError, match="at least one model"):
        CompareConfig(store=str(seq_store), out="o", models=())


def test_cli_compare(seq_store, checkpoints, tmp_path, capsys):
    from pipelines.cli import main as cli

    code = cli(["compare", "--store", str(seq_store), "--out", str(tmp_path), "--baseline",
                f"SMVA-Net={checkpoints['smvanet']}", "--max-frames", "1", "--pictures", "0", "--no-progress"])
    assert code == 0 and (tmp_path / "compare.md").is_file()
    assert "SMVA-Net" in capsys.readouterr().out
    assert cli(["compare", "--store", str(seq_store), "--out", str(tmp_path), "--baseline", "no-name.pt"]) == 2
    assert "NAME=CHECKPOINT" in capsys.readouterr().err


def test_an_erasenet_that_reads_history_gets_its_earlier_frames_and_sets_the_window(seq_store, checkpoints,
                                                                                    tmp_path):
    from models.erasenet.model import EraseNet

    history = save_tiny_checkpoints(seq_store, tmp_path / "ckpt", ("detector_history",))["detector_history"]
    spec = ModelSpec("ERASE-Net (history)", "erasenet", (history, checkpoints["segmenter"]))
    result = compare(CompareConfig(store=str(seq_store), out=str(tmp_path / "cmp"), models=(spec,), pictures=0,
                                   score_threshold=0.05, progress=False, command="radarseg compare ..."))
    assert result["window"] == 2 and result["frames"] == 5  # 6 test frames, each but the first has one before
    (row,) = result["models"]
    net = EraseNet.from_checkpoints(history, checkpoints["segmenter"], score_threshold=0.05)
    root = open_store(seq_store)
    slots = np.flatnonzero(root["split"][:] == 2)[1:]
    ra = np.zeros((4, 4), np.int64)
    for slot in slots:
        result = net.segment(root["input"][slot].astype(np.float32), kind=InputKind.log_power,
                             history=[root["input"][slot - 1].astype(np.float32)])
        ra += np.bincount(4 * root["ra_mask"][slot].astype(np.int64).ravel() + result.ra_mask.ravel(),
                          minlength=16).reshape(4, 4)
    np.testing.assert_array_equal(row["RA"]["confusion"], ra)
