"""A predictions store (a simulated recording's truth, tracked) and its three recordings, written once per session
by ``radarseg export recording``."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipelines.cli import main
from tests.pipelines.recordings.truth_store import write_truth_predictions


@pytest.fixture(scope="session")
def exported(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("recordings")
    store = write_truth_predictions(root, sequences=2, frames=3)
    paths = {"store": store, "mcap": root / "out.mcap", "rrd": root / "out.rrd", "ros2": root / "ros2.mcap"}
    assert main(["export", "recording", str(store), "--mcap", str(paths["mcap"]), "--rrd", str(paths["rrd"]),
                 "--ros2", str(paths["ros2"])]) == 0
    return paths


@pytest.fixture(scope="session")
def segmented(small_recording, tiny_checkpoints, tmp_path_factory) -> dict[str, Path]:
    """segment-batch's store of ``small_recording`` (tiny random-weight model, every centre kept) and its
    recordings."""
    from pipelines.inference.segment_batch import SegmentBatchConfig
    from pipelines.inference.segment_batch import main as segment_batch

    root = tmp_path_factory.mktemp("segmented")
    detector, segmenter = tiny_checkpoints
    store = root / "pred.zarr"
    segment_batch(SegmentBatchConfig(source=f"recording:{small_recording}", detector=str(detector),
                                     segmenter=str(segmenter), out=str(store), score_threshold=0.0, max_objects=3,
                                     progress=False, in_process=True))
    paths = {"store": store, "mcap": root / "out.mcap", "rrd": root / "out.rrd", "ros2": root / "ros2.mcap"}
    assert main(["export", "recording", str(store), "--mcap", str(paths["mcap"]), "--rrd", str(paths["rrd"]),
                 "--ros2", str(paths["ros2"])]) == 0
    return paths
