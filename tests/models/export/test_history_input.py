"""The exported detector reads the frame before as the PyTorch one does: on a store with history the ONNX engine's
labels and detections are the torch engine's, the int8 export takes the history input, and docs/onnx_example.py
feeds it."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from models.checkpoint import load_pair
from models.export.onnx_export import HISTORY_INPUTS, export_onnx
from models.runtime import load_erasenet
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.preprocess import PreprocessConfig
from pipelines.datasets.preprocess import main as preprocess
from pipelines.datasets.store import open_store
from radar import transforms
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

ROOT = Path(__file__).resolve().parents[3]
DETECTOR, SEGMENTER = ROOT / "checkpoints" / "detector.pt", ROOT / "checkpoints" / "segmenter.pt"


@pytest.fixture(scope="module")
def history_export(tmp_path_factory):
    """(store, float export dir) of the shipped pair (whose detector reads the frame before) and a store of 2
    sequences x 3 simulated frames (seed 41, built in process)."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("history")
    config = PreprocessConfig(source="sim", out=str(root / "store.zarr"), preset="small", sequences=2, frames=3,
                              seed=41, split_fractions=(1.0, 0.0, 0.0), shard_frames=3, progress=False)
    store = Path(preprocess(replace(config, in_process=True))["store"])
    detector, segmenter = load_pair(DETECTOR, SEGMENTER)
    export_onnx(detector, segmenter, root / "float")
    return store, root / "float"


def store_frames(store: Path, history_frames: int):
    """Each frame of the store: (log power, its earlier frames as the store gives them)."""
    root = open_store(store)
    earlier = earlier_slots(root, history_frames)
    for slot in range(root["input"].shape[0]):
        yield root["input"][slot].astype(np.float32), earlier_frames(root["input"], earlier[slot])


@pytest.mark.slow
def test_onnx_labels_and_detections_equal_torch_on_a_store_with_history(history_export):
    store, float_dir = history_export
    manifest = json.loads((float_dir / "manifest.json").read_text())
    torch_net = load_erasenet(DETECTOR, SEGMENTER)
    onnx_net = load_erasenet(DETECTOR, SEGMENTER, runtime="onnx", onnx_dir=float_dir)
    assert torch_net.history_frames == onnx_net.history_frames == manifest["detector"]["history_frames"] == 1
    assert list(manifest["detector"]["inputs"]) == ["log_power", *HISTORY_INPUTS]
    same = total = with_history = history_moved = 0
    for log_power, history in store_frames(store, onnx_net.history_frames):
        want = torch_net.segment(log_power, kind=InputKind.log_power, history=history)
        got = onnx_net.segment(log_power, kind=InputKind.log_power, history=history)
        assert len(got.centres) == len(want.centres)  # the same detections
        for name in ("score", "range_bin", "angle_bin", "doppler_bin"):
            np.testing.assert_allclose(getattr(got.centres, name), getattr(want.centres, name), atol=1e-3)
        assert [(o.class_id, o.n_voxels) for o in got.objects] == [(o.class_id, o.n_voxels) for o in want.objects]
        roi = (want.labels > 0) | (got.labels > 0)
        same += int(np.count_nonzero(got.labels[roi] == want.labels[roi]))
        total += int(np.count_nonzero(roi))
        if history[0] is not None:  # the earlier frame reaches the graph: its heatmap is not the single cube's
            with_history += 1
            alone = onnx_net._run_detector(log_power)["heatmap"]
            read = onnx_net._run_detector(log_power, **onnx_net._history_input(history))["heatmap"]
            history_moved += not torch.allclose(alone, read, atol=1e-4)
    assert total > 0 and same / total >= 0.999
    assert with_history == 4 and history_moved == with_history


def test_the_onnx_engine_refuses_history_it_cannot_read(history_export):
    _, float_dir = history_export
    onnx_net = load_erasenet(DETECTOR, SEGMENTER, runtime="onnx", onnx_dir=float_dir)
    cube = np.zeros(onnx_net.profile.shape, np.float32)
    with pytest.raises(ValueError, match="2 earlier frames given, the detector reads 1"):
        onnx_net.segment(cube, kind=InputKind.log_power, history=[cube, cube])
    with pytest.raises(ValueError, match="an earlier frame must have the cube's shape"):
        onnx_net.segment(cube, kind=InputKind.log_power, history=[cube[:-1]])


@pytest.mark.slow
def test_the_int8_detector_takes_the_history_input(history_export, tmp_path):
    """The int8 export's calibration feeds the detector graph the frame before each (as the float pipeline does);
    the detector quantised on them reads the history input and finds the float graph's seeds."""
    from models.export.onnx_engine import OnnxDetector, _session
    from models.export.quantize import float_pipeline_feeds, quantize_graph

    _, float_dir = history_export
    detector, segmenter = load_pair(DETECTOR, SEGMENTER)
    cubes = [transforms.log_power(frame.cube) for frame in simulate_sequence("small", 3, seed=77)]
    feeds, _, _ = float_pipeline_feeds(float_dir, detector, segmenter, cubes)
    assert [list(feed) for feed in feeds] == [["log_power", *HISTORY_INPUTS]] * 3
    assert [feed["history_present"].tolist() for feed in feeds] == [[0.0], [1.0], [1.0]]
    np.testing.assert_array_equal(feeds[2]["history"][0], cubes[1])
    quantize_graph(float_dir / "detector.onnx", tmp_path / "detector.onnx", feeds, "MinMax")
    net = detector.build().eval()
    graphs = {name: OnnxDetector(_session(path, 1), net)
              for name, path in (("float", float_dir / "detector.onnx"), ("int8", tmp_path / "detector.onnx"))}
    assert graphs["int8"].history_frames == 1
    for feed in feeds[1:]:
        found = {name: graph.decode(graph(feed["log_power"], feed["history"], feed["history_present"]), k=32,
                                    score_threshold=0.3)[0] for name, graph in graphs.items()}
        assert len(found["float"]["score"]) > 0
        np.testing.assert_allclose(found["int8"]["range_bin"], found["float"]["range_bin"], atol=1.0)


@pytest.mark.slow
def test_the_documented_example_feeds_the_frame_before(history_export, tmp_path):
    """docs/onnx_example.py given the frame before labels the ROI as the torch engine does with that history."""
    from tests.models.export.test_onnx_export import run_documented_example

    _, float_dir = history_export
    torch_net = load_erasenet(DETECTOR, SEGMENTER)
    before, frame = simulate_sequence("small", 2, seed=2026, sequence_index=1)
    np.save(tmp_path / "before.npy", before.cube)
    labels = run_documented_example(float_dir, frame.cube, tmp_path, earlier=[tmp_path / "before.npy"])
    expected = torch_net.segment(frame.cube, history=[transforms.log_power(before.cube)])
    roi = (expected.labels > 0) | (labels > 0)
    assert roi.any() and (labels[roi] == expected.labels[roi]).mean() >= 0.999
