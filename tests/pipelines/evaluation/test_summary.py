"""`radarseg models summary`: the shipped checkpoints' figures by default, a given checkpoint's, merged MAC columns."""

from __future__ import annotations

import json

import pytest
import torch

from models.checkpoint import Checkpoint, save_checkpoint
from models.registry import create_model
from pipelines.cli import main
from pipelines.evaluation.summary import SHIPPED, format_summary
from radar.profiles import get_profile


def test_default_rows_are_the_shipped_checkpoints(capsys):
    assert main(["models", "summary", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["source"].rsplit("/", 2)[-2:] for r in rows] == [["checkpoints", p.name] for p in SHIPPED]
    detector, segmenter = rows
    assert detector["model"] == "centre_detector" and segmenter["model"] == "minkunet"
    # The shipped, ratio-0.25 MinkUNet (1.36 M), not the paper-size one (2.92 M).
    assert 1.2e6 < segmenter["params"] < 1.5e6
    # the shipped detector: the paper's smaller backbone with a 12-channel Doppler compression that also reads the
    # frame before (0.147 G; 0.131 G on one frame, 0.116 G with the paper's 3 channels)
    assert 0.14e9 < detector["macs"] < 0.155e9


def test_a_given_checkpoint_is_described(tmp_path, capsys):
    torch.manual_seed(0)
    model = create_model("centre_detector_tiny", preset="small")
    path = save_checkpoint(Checkpoint(model_name="centre_detector_tiny", config={"preset": "small"},
                                      state_dict=model.state_dict(), preset="small",
                                      class_names=tuple(get_profile("small").all_class_names)), tmp_path / "d.pt")
    assert main(["models", "summary", "--checkpoint", str(path), "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["model"] == "centre_detector_tiny" and row["params"] == sum(p.numel() for p in model.parameters())


def test_the_paper_column_shows_only_where_the_counters_differ():
    rows = [{"model": "a", "source": "s", "preset": "small", "params": 1e6, "macs": 2e9, "macs_paper": 2e9,
             "input": "x"},
            {"model": "b", "source": "s", "preset": "small", "params": 1e6, "macs": 2e9, "macs_paper": 5e9,
             "input": "x"}]
    a, b = format_summary(rows).splitlines()[1:3]
    assert "same" in a and "5.000" not in a
    assert "5.000" in b and "same" not in b


def test_a_baseline_checkpoint_is_a_clear_error(tmp_path, capsys):
    pytest.importorskip("models.baselines")
    model = create_model("unet_tiny", preset="small")
    path = save_checkpoint(Checkpoint(model_name="unet_tiny", config={"preset": "small"},
                                      state_dict=model.state_dict(), preset="small",
                                      class_names=tuple(get_profile("small").all_class_names)), tmp_path / "u.pt")
    assert main(["models", "summary", "--checkpoint", str(path)]) == 2
    assert "expected a detector or a sparse segmenter checkpoint" in capsys.readouterr().err


def test_the_registry_rows_run_in_a_fresh_interpreter():
    """The shipped checkpoints load first (under a meta-device context, models.checkpoint), and the registry's
    SPVCNN is imported after: its module-level tensors must still be real (a fresh `radarseg models summary
    --profile small` once failed with 'Cannot copy out of meta tensor')."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "pipelines.cli", "models", "summary", "--profile", "small", "--json"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = json.loads(done.stdout)
    assert {row["model"] for row in rows if row["preset"] == "small"} >= {"centre_detector", "minkunet", "spvcnn"}
    assert all(row["macs"] > 0 for row in rows)
