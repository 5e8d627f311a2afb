"""``radarseg train class-offsets``: an offset per class on a segmenter's logits, chosen on a store's frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.runtime import load_erasenet
from pipelines.cli import main as cli
from pipelines.datasets.store import CENTRE_COLUMNS, open_store
from pipelines.training.class_offsets import CLASSIFIER_BIAS, FrameLogits, choose_offsets, objective, score
from radar import transforms
from radar.centres import Centres
from radar.input_kind import InputKind

REPO = Path(__file__).resolve().parents[3]
SHAPE = (16, 8, 4)  # (R, A, D) of the planted frames
CLASSES = 4  # background, pedestrian, cyclist, car


def planted_frames(pedestrian_bias: float, n_frames: int = 6, seed: int = 0) -> list[FrameLogits]:
    """Frames whose ROI is every voxel of a small cube, one pedestrian and one car object in each; logits that
    pick the true class by a margin of 1, except that ``pedestrian_bias`` is added to the pedestrian logit of
    every voxel (a segmenter that over-predicts pedestrians when it is positive)."""
    rng = np.random.default_rng(seed)
    voxels = np.stack(np.meshgrid(*map(np.arange, SHAPE), indexing="ij"), -1).reshape(-1, 3)
    frames = []
    for _ in range(n_frames):
        labels = np.zeros(SHAPE, np.uint8)
        r, a = rng.integers(0, SHAPE[0] - 2), rng.integers(0, SHAPE[1] - 2)
        labels[r:r + 2, a:a + 2, 1] = 1  # a pedestrian, 4 voxels
        labels[(r + 5) % (SHAPE[0] - 3):(r + 5) % (SHAPE[0] - 3) + 3, :3, 2:] = 3  # a car
        truth_classes = labels[tuple(voxels.T)]
        logits = rng.normal(0, 0.1, (len(voxels), CLASSES)).astype(np.float32)
        logits[np.arange(len(voxels)), truth_classes] += 1.0
        logits[:, 1] += pedestrian_bias
        truth = {"ra": transforms.project_ra(labels, CLASSES), "rd": transforms.project_rd(labels, CLASSES)}
        frames.append(FrameLogits(voxels, logits, np.arange(len(voxels)), truth))
    return frames


def test_offsets_undo_a_planted_bias_and_raise_the_objective():
    frames = planted_frames(pedestrian_bias=0.9)
    before = objective(score(frames, np.zeros(CLASSES, np.float32), SHAPE))
    offsets, moves = choose_offsets(frames, CLASSES, SHAPE)
    after = objective(score(frames, offsets, SHAPE))
    assert offsets[0] == 0 and offsets[1] <= -0.5, offsets  # the pedestrian logit brought down
    assert after > before + 0.05 and moves[-1]["objective"] == pytest.approx(after)
    assert moves[0]["offsets"] == [0.0] * CLASSES and [m["objective"] for m in moves] == sorted(
        m["objective"] for m in moves)


def test_a_calibrated_segmenter_keeps_zero_offsets():
    frames = planted_frames(pedestrian_bias=0.0)
    offsets, moves = choose_offsets(frames, CLASSES, SHAPE)
    assert objective(score(frames, np.zeros(CLASSES, np.float32), SHAPE)) == pytest.approx(1.0)
    assert not offsets.any() and len(moves) == 1


def test_score_projects_the_offset_argmax():
    frames = planted_frames(pedestrian_bias=0.0, n_frames=1)
    no_foreground = score(frames, np.array([0, -100, -100, -100], np.float32), SHAPE)
    for view in ("ra", "rd"):
        matrix = no_foreground.matrices[view]
        assert matrix[:, 1:].sum() == 0 and matrix.sum() == frames[0].truth[view].size


def test_the_cli_writes_the_offsets_into_the_classifier_bias(small_store, tmp_path, caplog):
    """The shipped pair, its segmenter's car logit raised by 1.5 (a segmenter that labels cars all over the ROI;
    cars are most of the store's objects): the offsets chosen bring it back down, and the copy labels as logits +
    offsets."""
    detector = str(REPO / "checkpoints" / "detector.pt")
    shipped = load_checkpoint(REPO / "checkpoints" / "segmenter.pt")
    state = dict(shipped.state_dict)
    state[CLASSIFIER_BIAS] = state[CLASSIFIER_BIAS] + torch.tensor([0, 0, 0, 1.5], dtype=state[CLASSIFIER_BIAS].dtype)
    segmenter, target = tmp_path / "biased.pt", tmp_path / "tuned.pt"
    save_checkpoint(dataclasses.replace(shipped, state_dict=state), segmenter)
    assert cli(["train", "class-offsets", str(segmenter), str(target), "--store", str(small_store),
                "--store", str(small_store), "--detector", detector, "--split", "all", "--no-progress"]) == 0
    source, tuned = load_checkpoint(segmenter), load_checkpoint(target)
    assert "class offsets chosen on 12 frames" in caplog.text  # few frames: the user is told
    record = tuned.extra["class_offsets"]
    offsets = torch.tensor([record["offsets"][name] for name in tuned.class_names])
    earlier = shipped.extra.get("class_offsets", {}).get("total", {})  # the shipped segmenter's own offsets
    assert record["frames"] == 12 and record["offsets"]["background"] == 0
    assert record["total"] == {name: earlier.get(name, 0.0) + record["offsets"][name] for name in tuned.class_names}
    assert record["offsets"]["car"] <= -1.0, record["offsets"]
    torch.testing.assert_close(tuned.state_dict[CLASSIFIER_BIAS].float(),  # float16 weights: rounded
                               source.state_dict[CLASSIFIER_BIAS].float() + offsets, atol=2e-3, rtol=0)
    assert record["after"]["RA"]["mIoU"] + record["after"]["RD"]["mIoU"] > (
        record["before"]["RA"]["mIoU"] + record["before"]["RD"]["mIoU"]) + 0.05
    # the tuned segmenter labels every ROI voxel as the source's logits plus the offsets (true centres: a ROI)
    root = open_store(small_store)
    cube = root["input"][0].astype(np.float32)
    centres = Centres.from_bins(root["objects"][0][: int(root["n_objects"][0])][:, CENTRE_COLUMNS].astype(np.float64))
    plain, shifted = load_erasenet(detector, segmenter), load_erasenet(detector, target)
    result = shifted.segment(cube, kind=InputKind.log_power, centres=centres)
    assert len(result.regions) > 100 and (result.labels == 1).any()
    logits, inverse, _, _ = plain.point_logits(result.regions, cube)
    expected = (logits + offsets).argmax(1).numpy()[inverse]
    same = result.labels[tuple(result.regions.voxels.T)] == expected  # the bias rounded to float16: near ties
    assert same.mean() > 0.999 and (expected != logits.argmax(1).numpy()[inverse]).any()


def test_bad_arguments_are_refused(small_store, tiny_checkpoints, tmp_path, capsys):
    detector, segmenter = tiny_checkpoints
    base = ["train", "class-offsets", str(segmenter), str(tmp_path / "t.pt"), "--store", str(small_store)]
    assert cli([*base, "--detector", str(detector), "--frames", "-1"]) != 0
    assert "--frames must be >= 0" in capsys.readouterr().err
    assert cli([*base, "--detector", str(detector), "--threads", "-2"]) != 0
    assert "--threads must be >= 0" in capsys.readouterr().err
    assert cli([*base, "--detector", str(segmenter)]) != 0  # a segmenter where the detector belongs
    assert "--detector" in capsys.readouterr().err
    assert cli([*base, "--detector", str(detector), "--split", "test"]) != 0  # the store has no test split
    assert "has no frames" in capsys.readouterr().err
    assert not (tmp_path / "t.pt").exists()
