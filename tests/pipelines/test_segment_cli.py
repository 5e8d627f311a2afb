import json

import numpy as np
import torch

from models.checkpoint import Checkpoint, save_checkpoint
from models.registry import create_model
from pipelines.cli import main
from radar.simulate import simulate_sequence

CLASSES = ("background", "pedestrian", "cyclist", "car")


def _checkpoints(tmp_path):
    torch.manual_seed(0)
    det = create_model("centre_detector_tiny", preset="small")
    seg = create_model("minkunet_tiny", preset="small")
    return (save_checkpoint(Checkpoint("centre_detector_tiny", {"preset": "small"}, det.state_dict(), "small", CLASSES,
                                       {"mean": 60.0, "std": 8.0}), tmp_path / "det.pt"),
            save_checkpoint(Checkpoint("minkunet_tiny", {"preset": "small"}, seg.state_dict(), "small", CLASSES),
                            tmp_path / "seg.pt"))


def test_segment_command_prints_objects_compute_and_draws(tmp_path, capsys):
    det, seg = _checkpoints(tmp_path)
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, next(simulate_sequence("small", 1, seed=2)).cube)
    png = tmp_path / "pred.png"
    code = main(["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg), "--score-threshold", "0",
                 "--png", str(png), "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    macs = out["compute"]["macs"]
    assert macs["total"] == macs["detect"] + macs["segment"] + macs["grow"] > 0
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_segment_command_refuses_a_wrong_cube(tmp_path, capsys):
    det, seg = _checkpoints(tmp_path)
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, np.zeros((64, 128, 32), np.complex64))
    assert main(["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg)]) == 2
    assert "expected (128, 128, 32)" in capsys.readouterr().err
