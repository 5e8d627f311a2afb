"""Training output stays out of `ray job submit --working-dir .`, and an oversized upload is one line naming why."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from pipelines.cli import main
from pipelines.upload_check import check_upload

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
@pytest.mark.parametrize("path", ["runs/det/last.pt", "cube.npy", "frame_adc.npy", "frame_rad.npy", "my_radar.toml",
                                  "viewer.png",
                                  "out/train/x.zarr", "data/small.zarr"])
def test_what_the_readme_commands_write_is_ignored(path):
    assert subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO).returncode == 0, path


def _tree(root: Path, ignore: str) -> None:
    (root / "runs" / "det").mkdir(parents=True)
    (root / "runs" / "det" / "last.pt").write_bytes(b"\0" * 300_000)
    (root / "code.py").write_text("print('hi')\n")
    (root / ".gitignore").write_text(ignore)


def test_an_oversized_working_dir_is_one_line_naming_the_largest_file(tmp_path, capsys):
    _tree(tmp_path, "")
    assert main(["upload-check", str(tmp_path), "--limit-mib", "0.25"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "runs/det/last.pt 0.3 MiB" in err and "HTTP 413" in err and '"excludes": ["runs/"]' in err
    # The excludes of --runtime-env-json, or .gitignore, take it out of the upload.
    assert main(["upload-check", str(tmp_path), "--limit-mib", "0.25", "--exclude", "runs/"]) == 0
    assert check_upload(tmp_path)["files"] == 3  # nothing excluded: code, .gitignore, last.pt
    (tmp_path / ".git").mkdir()  # Ray never uploads .git (nor .venv, __pycache__), and neither does the check
    (tmp_path / ".git" / "pack").write_bytes(b"\0" * 300_000)
    assert check_upload(tmp_path)["files"] == 3
    (tmp_path / ".gitignore").write_text("runs/\n")
    assert check_upload(tmp_path, limit_bytes=250_000)["files"] == 2


def test_a_missing_directory_is_a_clear_error(tmp_path, capsys):
    assert main(["upload-check", str(tmp_path / "nope")]) == 2
    assert "expected the --working-dir to check" in capsys.readouterr().err
