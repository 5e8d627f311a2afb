import json

import numpy as np

from pipelines.cli import main
from radar.simulate import simulate_sequence

CLASSES = ("background", "pedestrian", "cyclist", "car")


def test_segment_command_prints_objects_compute_and_draws(tmp_path, capsys, tiny_checkpoints):
    det, seg = tiny_checkpoints
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


def test_segment_command_refuses_a_wrong_cube(tmp_path, capsys, tiny_checkpoints):
    det, seg = tiny_checkpoints
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, np.zeros((64, 128, 32), np.complex64))
    assert main(["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg)]) == 2
    assert "expected (128, 128, 32)" in capsys.readouterr().err


def test_segment_command_runs_the_onnx_engine_from_checkpoints_alone(tmp_path, capsys, monkeypatch, tiny_checkpoints):
    det, seg = tiny_checkpoints
    monkeypatch.setenv("RADARSEG_ONNX_CACHE", str(tmp_path / "cache"))
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, next(simulate_sequence("small", 1, seed=2)).cube)
    args = ["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg), "--score-threshold", "0",
            "--json"]
    assert main([*args, "--runtime", "onnx"]) == 0
    onnx = json.loads(capsys.readouterr().out)
    assert main(args) == 0
    torch = json.loads(capsys.readouterr().out)
    assert onnx["compute"]["runtime"] == "onnx" and torch["compute"]["runtime"] == "torch"
    assert onnx["compute"]["macs"] == torch["compute"]["macs"]
    assert [o["class_name"] for o in onnx["objects"]] == [o["class_name"] for o in torch["objects"]]
    assert len(list((tmp_path / "cache").glob("*/manifest.json"))) == 1  # exported on first use, into the cache
