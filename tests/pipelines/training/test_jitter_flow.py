"""The README's stage-2 command with a detector that matches nothing: one line explaining what the measurement
needed and offering --jitter-std, and no run directory left behind; in smoke mode the path runs on, said aloud."""

from __future__ import annotations

import logging

from pipelines.cli import main
from tests.conftest import save_tiny_checkpoints


def test_jitter_from_a_detector_that_matches_nothing(small_store, tmp_path, capsys, monkeypatch, caplog):
    made = save_tiny_checkpoints(small_store, tmp_path / "ckpt", ("detector",))
    argv = ["train", "segmenter", "--store", str(small_store), "--jitter-from", made["detector"], "--max-steps", "1",
            "--model", "minkunet_tiny", "--model-config", "{}", "--no-progress", "--threads", "1"]
    assert main([*argv, "--out", str(tmp_path / "seg")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "matched none of the" in err and "--jitter-std R A D" in err
    assert not (tmp_path / "seg").exists()

    monkeypatch.setenv("RADARSEG_SMOKE", "1")
    assert main([*argv, "--out", str(tmp_path / "seg-smoke")]) == 0
    assert (tmp_path / "seg-smoke" / "model.pt").is_file()
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and "jitter" in r.getMessage()]
    assert len(warnings) == 1, warnings  # the smoke rule's, not also "neither --jitter-from nor --jitter-std given"
    assert "smoke mode" in warnings[0] and "--jitter-std" in warnings[0] and made["detector"] in warnings[0]
