"""``--runtime torch-int8`` on the command line: segment and evaluate run the segmenter in the int8 sparse kernels (tiny
checkpoints, whose widths are not multiples of 4: padded inside); the former ``--precision int8`` says the new
option, and an option that disagrees with it is refused in one line."""

from __future__ import annotations

import json

import numpy as np
import torch

from models.export import quantize
from pipelines.cli import main
from radar.simulate import simulate_sequence


def test_segment_runs_in_int8(tmp_path, capsys, monkeypatch, tiny_checkpoints):
    monkeypatch.setattr(quantize, "CALIBRATION_FRAMES", 2)  # calibration frames simulated at load: fewer, faster
    det, seg = tiny_checkpoints
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, next(simulate_sequence("small", 1, seed=2)).cube)
    args = ["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg), "--score-threshold", "0",
            "--json", "--no-warm-up"]
    assert main([*args, "--runtime", "torch-int8"]) == 0
    int8 = json.loads(capsys.readouterr().out)
    assert main(args) == 0
    float_ = json.loads(capsys.readouterr().out)
    assert int8["runtime"] == "torch-int8" and float_["runtime"] == "torch"
    assert int8["compute"]["macs"] == float_["compute"]["macs"]  # the same ROI, the same pairs and widths
    assert int8["compute"]["roi_voxels"] == float_["compute"]["roi_voxels"] > 0


def test_a_former_option_that_disagrees_with_the_runtime_is_refused_in_one_line(tmp_path, capsys,
                                                                                tiny_checkpoints):
    det, seg = tiny_checkpoints
    cube_path = tmp_path / "cube.npy"
    np.save(cube_path, next(simulate_sequence("small", 1, seed=2)).cube)
    code = main(["segment", str(cube_path), "--detector", str(det), "--segmenter", str(seg), "--runtime", "torch",
                 "--precision", "int8"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--runtime torch and the former --engine/--precision (torch-int8) disagree" in err
    assert "Traceback" not in err


def test_evaluate_runs_in_int8(small_store, tiny_checkpoints, tmp_path, capsys):
    detector, segmenter = tiny_checkpoints
    threads = torch.get_num_threads()
    try:
        code = main(["evaluate", "--detector", str(detector), "--segmenter", str(segmenter), "--store",
                     str(small_store), "--split", "val", "--out", str(tmp_path), "--max-frames", "1", "--pictures",
                     "0", "--sweep", "6", "--sweep-frames", "0", "--no-oracle", "--no-progress", "--threads", "1",
                     "--precision", "int8", "--score-threshold", "0"])  # the former option, still accepted
    finally:
        torch.set_num_threads(threads)
    assert code == 0 and (tmp_path / "report.md").is_file()
    assert "mAP" in capsys.readouterr().out
