import os

import pytest

os.environ.setdefault("RAY_AUTH_MODE", "disabled")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory):
    """A tiny simulated recording (small preset, 2 sequences x 3 frames) shared by reader tests."""
    from pipelines.record import simulate_recording

    out = tmp_path_factory.mktemp("rec") / "small"
    return simulate_recording(preset="small", sequences=2, frames=3, seed=11, out=out, progress=False)
