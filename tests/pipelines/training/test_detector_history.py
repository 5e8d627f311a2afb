"""Training a detector that reads earlier frames: it learns from histories and is scored both ways."""

import json

import torch

from models.checkpoint import load_checkpoint
from pipelines.cli import main as cli


def test_a_history_detector_trains_and_is_scored_with_history_and_on_single_cubes(small_store, tmp_path):
    run = tmp_path / "det"
    assert cli(["train", "detector", "--store", str(small_store), "--out", str(run), "--model",
                "centre_detector_tiny", "--model-config", '{"history_frames": 1}', "--batch-size", "2",
                "--max-steps", "2", "--no-progress"]) == 0
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    for name in ("val_mAP", "val_mAP_single", "val_recall_car_single"):
        assert 0.0 <= last[name] <= 1.0, name
    checkpoint = load_checkpoint(run / "model.pt")
    assert checkpoint.config["history_frames"] == 1
    detector = checkpoint.build().eval()
    with torch.no_grad():
        alone = detector(torch.zeros(1, 32, 128, 128))
        earlier = detector(torch.zeros(1, 32, 128, 128), history=torch.ones(1, 1, 32, 128, 128))
    assert (alone["heatmap_logits"] - earlier["heatmap_logits"]).abs().max() > 0  # the history is read
