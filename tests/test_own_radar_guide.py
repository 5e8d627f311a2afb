"""The own-radar guide (docs/guides/own-radar.md) runs as written, from a profile file to a served model and
its ONNX graphs, and the radar travels under its own name: in the store, both checkpoints, the ONNX manifest and
the service.

The page's first block runs in order, in smoke mode, in a directory laid out like a clone (the runner of
tests/test_documented_commands.py, which leaves this path to this test); then what each step left is checked.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest

from tests.test_documented_commands import REPO, Runner, documented_commands

GUIDE = "docs/guides/own-radar.md"
RADAR = "myradar"  # the name in docs/profiles/my_radar.toml


def own_radar_commands() -> list:
    """The commands of the guide :data:`GUIDE`'s first ``bash`` block (the path), in order."""
    commands = documented_commands((GUIDE,))
    return [c for c in commands if c.block == commands[0].block]


def test_the_section_takes_a_profile_file_through_train_evaluate_export_and_serve():
    text = " ".join(c.text for c in own_radar_commands())
    for step in ("radar tune-growing", "preprocess", "train detector", "train segmenter", "evaluate",
                 "export onnx", "serve", "curl"):
        assert step in text, f"the own-radar path lacks `{step}`"


@pytest.mark.slow
def test_the_own_radar_path_runs_as_written_and_keeps_the_radars_name(tmp_path):
    root = tmp_path / "clone"
    root.mkdir()
    for name in (".venv", "radar", "models", "pipelines", "process", "service", "docs", "pyproject.toml",
                 ".gitignore"):
        (root / name).symlink_to(REPO / name)
    runner = Runner(root)
    try:
        for command in own_radar_commands():
            problem = runner.run(command)
            assert problem is None, f"{command}\n    {problem}"
            if command.words[1:2] == ("serve",):
                with urllib.request.urlopen(f"{runner.url()}/v1/models", timeout=30) as answer:
                    served = json.loads(answer.read())
    finally:
        runner.stop()
    profile = (root / "my_radar.toml").read_text()
    assert "[region_growing]" in profile  # tune-growing --write put the derived settings into the copy

    from models.checkpoint import load_checkpoint
    from pipelines.datasets.store_info import StoreInfo

    store = StoreInfo.read(root / "data" / "mine.zarr")
    assert store.profile.name == RADAR and dict(store.profile.region_growing)
    for stage in ("det", "seg"):
        checkpoint = load_checkpoint(root / "runs" / f"mine-{stage}" / "model.pt")
        assert checkpoint.preset == RADAR and checkpoint.extra["radar_file"]["name"] == RADAR
        assert checkpoint.profile == store.profile
    manifest = json.loads((root / "runs" / "mine-onnx" / "manifest.json").read_text())
    assert manifest["preset"] == RADAR and manifest["radar_file"]["region_growing"]
    models = {m["name"]: m for m in served["models"]}
    assert RADAR in models and models[RADAR]["preset"] == RADAR, served
    metrics = json.loads((root / "runs" / "mine-eval" / "metrics.json").read_text())
    assert metrics["preset"] == RADAR


def test_a_checkpoint_without_the_radar_still_loads_for_a_built_in_preset():
    """Checkpoints made before radars travelled (the shipped ones) name a built-in preset and load as before."""
    from models.checkpoint import load_checkpoint

    checkpoint = load_checkpoint(Path(REPO) / "checkpoints" / "detector.pt")
    assert "radar_file" not in checkpoint.extra and checkpoint.profile.name == "small"
    assert checkpoint.build() is not None
