"""``radarseg train class-gains``: a threshold per class for a detector with a heatmap per class."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from models.checkpoint import load_checkpoint
from models.detector.centernet import CentreNetHead
from models.detector.targets import OUTPUT_STRIDE
from pipelines.cli import main as cli
from pipelines.datasets.store import OBJECT_COLUMN, StoreDataset
from pipelines.datasets.store_info import StoreInfo
from pipelines.training.class_gains import THRESHOLDS, ClassCounts, choose_gains, count_class_matches
from radar.centres import SCORE_THRESHOLD
from radar.errors import UserError


class PlantedDetector(nn.Module):
    """Outputs a heatmap per class with a peak of ``score[c]`` at each true object's centre cell, in its class's
    channel, exact offsets and Doppler: what a perfect detector with these confidences would give."""

    def __init__(self, store, split: str, scores: list[float]):
        super().__init__()
        self.head = CentreNetHead(doppler_bins=store.profile.n_doppler, heatmap_classes=3)
        self.frames = StoreDataset(store.path, split, fields=("input", "objects"), normalise=False)
        self.scores = scores
        self.calls = 0

    def forward(self, log_power):
        batch, _, n_range, n_angle = log_power.shape
        h, w = -(-n_range // OUTPUT_STRIDE), -(-n_angle // OUTPUT_STRIDE)
        heat, offset, doppler = torch.zeros(batch, 3, h, w), torch.zeros(batch, 2, h, w), torch.zeros(batch, 1, h, w)
        for b in range(batch):
            sample = self.frames[self.calls + b]
            for row in sample["objects"][:int(sample["n_objects"])].double().numpy():
                r, a = row[OBJECT_COLUMN["range_bin"]] / OUTPUT_STRIDE, row[OBJECT_COLUMN["angle_bin"]] / OUTPUT_STRIDE
                cell = (int(r), int(a))
                c = int(row[OBJECT_COLUMN["class_id"]]) - 1
                heat[b, c, cell[0], cell[1]] = self.scores[c]
                offset[b, :, cell[0], cell[1]] = torch.tensor([r - cell[0], a - cell[1]])
                doppler[b, 0, cell[0], cell[1]] = row[OBJECT_COLUMN["doppler_bin"]]
        self.calls += batch
        return {"class_heatmap": heat, "heatmap": heat.amax(1, keepdim=True), "offset": offset, "doppler": doppler}

    def decode(self, outputs, k, score_threshold):
        return self.head.decode(outputs, k=k, score_threshold=score_threshold)


def test_counts_of_a_planted_detector_and_the_chosen_thresholds(small_store):
    store = StoreInfo.read(small_store)
    detector = PlantedDetector(store, "train", [0.21, 0.46, 0.9])
    counts, frames = count_class_matches(detector, {"mean": 0.0, "std": 1.0}, store, "train", batch_size=2)
    dataset = StoreDataset(store.path, "train", fields=("objects",), normalise=False)
    classes = np.concatenate([dataset[i]["objects"][:int(dataset[i]["n_objects"]), OBJECT_COLUMN["class_id"]].numpy()
                              for i in range(len(dataset))])
    assert frames == len(dataset) and [c.name for c in counts] == list(store.class_names[1:])
    thresholds = np.asarray(THRESHOLDS)
    for c, count in enumerate(counts):
        assert count.truths == int((classes == c + 1).sum())
        expected = np.where(thresholds <= detector.scores[c], count.truths, 0)
        np.testing.assert_array_equal(count.matched, expected)  # every object found, and only below its score
        np.testing.assert_array_equal(count.kept, expected)  # no other peak in its channel
    chosen = choose_gains([cnt for cnt in counts if cnt.truths], frames)
    for name, record in chosen.items():
        c = list(store.class_names[1:]).index(name)
        # every threshold up to the planted score has F1 1: the highest of them is chosen
        highest = max(t for t in THRESHOLDS if t <= detector.scores[c])
        assert record["f1"] == 1.0 and record["threshold"] == highest
        assert record["gain"] == pytest.approx(SCORE_THRESHOLD / record["threshold"])


def test_best_f1_by_hand():
    kept = np.zeros(len(THRESHOLDS), np.int64)
    matched = np.zeros_like(kept)
    kept[:4], matched[:4] = [20, 12, 8, 4], [8, 7, 6, 3]  # 10 true objects; F1 = 2 m / (k + 10)
    chosen = choose_gains([ClassCounts("pedestrian", kept, matched, 10)], frames=5)["pedestrian"]
    f1 = [2 * m / (k + 10) for k, m in zip([20, 12, 8, 4], [8, 7, 6, 3], strict=True)]
    assert chosen["threshold"] == THRESHOLDS[int(np.argmax(f1))] == THRESHOLDS[2]
    assert chosen["f1"] == pytest.approx(max(f1)) and chosen["peaks_per_frame"] == pytest.approx(8 / 5)
    assert chosen["precision"] == pytest.approx(6 / 8) and chosen["recall"] == pytest.approx(0.6)


def test_cli_writes_the_gains_into_a_copy_and_refuses_a_one_heatmap_detector(small_store, tmp_path, capsys):
    run = tmp_path / "det"
    assert cli(["train", "detector", "--store", str(small_store), "--out", str(run), "--model",
                "centre_detector_tiny", "--model-config", '{"heatmap_classes": 3}', "--batch-size", "2",
                "--max-steps", "1", "--no-progress"]) == 0
    capsys.readouterr()
    tuned = tmp_path / "tuned.pt"
    assert cli(["train", "class-gains", str(run / "model.pt"), str(tuned), "--store", str(small_store)]) == 0
    printed = capsys.readouterr().out
    checkpoint = load_checkpoint(tuned)
    gains = checkpoint.state_dict["head.class_gain"].float()
    thresholds = checkpoint.extra["class_gains"]["thresholds"]
    assert list(thresholds) == ["pedestrian", "cyclist", "car"] and all(t in THRESHOLDS for t in thresholds.values())
    torch.testing.assert_close(gains, torch.tensor([SCORE_THRESHOLD / t for t in thresholds.values()]))
    for name, t in thresholds.items():
        assert f"{name} threshold {t:.3f}" in printed
    detector = checkpoint.build().eval()
    with torch.no_grad():
        out = detector(torch.zeros(1, 32, 128, 128))
    expected = (out["class_heatmap"] * gains[:, None, None]).clamp(max=1).amax(1, keepdim=True)
    torch.testing.assert_close(out["heatmap"], expected)
    plain = tmp_path / "plain"
    cli(["train", "detector", "--store", str(small_store), "--out", str(plain), "--model", "centre_detector_tiny",
         "--batch-size", "2", "--max-steps", "1", "--no-progress"])
    with pytest.raises(UserError, match="heatmap_classes"):
        from pipelines.training.class_gains import write_class_gains
        write_class_gains(plain / "model.pt", tmp_path / "x.pt", StoreInfo.read(small_store))
