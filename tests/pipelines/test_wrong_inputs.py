"""A newcomer's wrong inputs fail clearly: exit code 2 and one line on stderr naming what was given and what was
expected, never a traceback or torch's advice. Every case stops at the boundary (checkpoint metadata, the cube's
header and values, the options), before a network is built, so the whole file runs in seconds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipelines.cli import main
from radar import transforms
from radar.simulate import point_target_cube

REPO = Path(__file__).resolve().parents[2]
DET, SEG = str(REPO / "checkpoints" / "detector.pt"), str(REPO / "checkpoints" / "segmenter.pt")


@pytest.fixture(scope="module")
def cubes(tmp_path_factory) -> dict[str, str]:
    root = tmp_path_factory.mktemp("cubes")
    cube = point_target_cube("small", 20.0, 10.0, 3.0)
    arrays = {"complex": cube, "log_power": transforms.log_power(cube), "magnitude": np.abs(cube).astype(np.float32)}
    paths = {}
    for name, array in arrays.items():
        paths[name] = str(root / f"{name}.npy")
        np.save(paths[name], array)
    return paths


def _fails_clearly(capsys, argv: list[str], *expected: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "weights_only" not in err, err
    for text in expected:
        assert text in err, err
    return err


@pytest.mark.parametrize(("case", "expected"), [
    ("swapped", ("are swapped", "a segmenter checkpoint (minkunet")),
    ("detector twice", ("the same file", "expected a detector checkpoint and a segmenter checkpoint")),
    ("readme as detector", ("README.md: not a checkpoint", "expected a radarseg detector checkpoint")),
    ("log power without --input", ("real-valued float32 cube", "--input log_power")),
    ("linear magnitude as log power", ("linear magnitude or power?", "--input magnitude")),
    ("log power as magnitude", ("looks like log power in dB", "--input log_power")),
])
def test_segment_refuses_wrong_files_and_units(capsys, cubes, case, expected):
    detector, segmenter, cube, extra = DET, SEG, cubes["complex"], []
    if case == "swapped":
        detector, segmenter = SEG, DET
    elif case == "detector twice":
        segmenter = DET
    elif case == "readme as detector":
        detector = str(REPO / "README.md")
    elif case == "log power without --input":
        cube = cubes["log_power"]
    elif case == "linear magnitude as log power":
        cube, extra = cubes["magnitude"], ["--input", "log_power"]
    elif case == "log power as magnitude":
        cube, extra = cubes["log_power"], ["--input", "magnitude"]
    _fails_clearly(capsys, ["segment", cube, "--detector", detector, "--segmenter", segmenter, *extra], *expected)


def test_a_cube_of_another_radar_is_refused_naming_the_radar_the_model_is_for(capsys, tmp_path):
    other = tmp_path / "ti.npy"
    np.save(other, np.zeros((128, 64, 128), np.complex64))  # a TI radar's cube, not the small preset's
    _fails_clearly(capsys, ["segment", str(other), "--detector", DET, "--segmenter", SEG],
                   "has shape (128, 64, 128), expected (128, 128, 32)", "trained for the radar 'small'",
                   "docs/guides/own-radar.md")


def test_jobs_refuse_swapped_checkpoints_and_bad_options(capsys, tmp_path):
    recording = tmp_path / "rec"
    recording.mkdir()
    (recording / "recording.json").write_text("{}")
    _fails_clearly(capsys, ["evaluate", "--detector", SEG, "--segmenter", DET, "--store", str(recording),
                            "--out", str(tmp_path / "eval")], "--detector", "expected a detector checkpoint")
    _fails_clearly(capsys, ["segment-batch", "--source", f"store:{recording}", "--detector", DET, "--segmenter", DET,
                            "--out", str(tmp_path / "pred.zarr")], "expected a segmenter checkpoint")
    _fails_clearly(capsys, ["models", "summary", "--checkpoint", str(REPO / "README.md")], "not a checkpoint")
    _fails_clearly(capsys, ["prune", "--checkpoint", str(REPO / "README.md"), "--ratio", "0.4",
                            "--out", str(tmp_path / "p.pt")], "not a checkpoint")
    _fails_clearly(capsys, ["store", "info", str(recording)], "it is a recording: preprocess it first")
    _fails_clearly(capsys, ["train", "detector", "--store", str(recording), "--out", str(tmp_path / "run"),
                            "--batch-size", "1"], "--batch-size must be >= 2")
    assert not (tmp_path / "eval").exists()  # refused before anything was written
