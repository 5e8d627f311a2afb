"""The code version recorded with every store a job writes."""

from __future__ import annotations

import importlib.metadata
import subprocess
from pathlib import Path
from typing import Any


def code_version() -> dict[str, Any]:
    """Package version and, when run from a git checkout, the commit (and whether the tree is dirty)."""
    try:
        package = importlib.metadata.version("radarseg")
    except importlib.metadata.PackageNotFoundError:
        package = None
    repo = Path(__file__).resolve().parents[2]
    commit = dirty = None
    if (repo / ".git").exists():
        try:
            commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True,
                                    check=True, timeout=10).stdout.strip()
            dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                                        capture_output=True, text=True, check=True, timeout=10).stdout.strip())
        except (OSError, subprocess.SubprocessError):
            commit = dirty = None
    return {"package": package, "git_commit": commit, "git_dirty": dirty}
