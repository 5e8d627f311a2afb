"""int8 export: the quantised graphs are standard ONNX, agree with the float graphs on the labels of the ROI
voxels and find the same objects on fixed simulated frames, and the export cache keys on the calibration."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from models.checkpoint import load_pair
from models.export.export_cache import Int8Calibration, exported_dir
from models.export.onnx_export import export_onnx, validate
from models.export.quantize import export_int8, roi_label_agreement, simulated_calibration_frames
from models.runtime import load_erasenet
from radar.simulate import simulate_sequence

ROOT = Path(__file__).resolve().parents[3]
DETECTOR, SEGMENTER = ROOT / "checkpoints" / "detector.pt", ROOT / "checkpoints" / "segmenter.pt"
# One worker runs the whole module, so the int8 export (about 40 CPU seconds) is built once, not once per worker.
pytestmark = pytest.mark.xdist_group("int8_export")


@pytest.fixture(scope="module")
def int8_export(tmp_path_factory):
    """(float dir, int8 dir) of the shipped pair, calibrated with MinMax on 4 simulated frames."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("int8")
    detector, segmenter = load_pair(DETECTOR, SEGMENTER)
    export_onnx(detector, segmenter, root / "float")
    cubes, description = simulated_calibration_frames("small", 4)
    export_int8(detector, segmenter, root / "int8", cubes=cubes, calibration=description, methods=("MinMax",),
                float_dir=root / "float")
    return root / "float", root / "int8"


def test_int8_graphs_are_standard_onnx_and_the_manifest_names_their_precision(int8_export):
    float_dir, int8_dir = int8_export
    manifest = json.loads((int8_dir / "manifest.json").read_text())
    assert manifest["precision"] == "int8" and manifest["quantization"]["method"] == "MinMax"
    assert manifest["quantization"]["calibration"]["source"] == "simulated"
    # the detector is int8 only where it ran faster than float compute on int8 weights (what ships otherwise: a
    # quarter of the weight bytes, folded into float weights when the session is built) on the calibration frames
    timed = manifest["quantization"]["detector_ms_one_thread"]
    detector_int8 = timed["int8"] < timed["int8-weights"]
    assert timed["chosen"] == "measured"
    assert manifest["detector"]["precision"] == manifest["quantization"]["graphs"]["detector"] == \
        ("int8" if detector_int8 else "int8-weights")
    assert manifest["segmenter"]["precision"] == "int8"
    for stage in ("detector", "segmenter"):
        checked = validate(int8_dir / manifest[stage]["file"])  # the checker, and no operator outside ai.onnx
        if stage == "segmenter" or detector_int8:
            assert {"QuantizeLinear", "DequantizeLinear"} <= set(checked["operators"])
            assert manifest[stage]["bytes"] < 0.5 * manifest[stage]["float_bytes"]
        else:
            assert "QuantizeLinear" not in checked["operators"] and "DequantizeLinear" in checked["operators"]
            assert manifest[stage]["bytes"] < 0.5 * manifest[stage]["float_bytes"]
    assert "z-columns" in manifest["quantization"]["segmenter_form"]  # quantised from the column-gather form
    precision = manifest["segmenter"]["operator_precision"]
    assert precision["Gemm"].get("int8", 0) > 0 and precision["Gather"].get("int8", 0) > 0
    assert precision["Gather"].get("index", 0) > 0  # shape arithmetic stays integer
    assert precision["Add"].get("float", 0) > 0 and "int8" not in precision["Add"]  # the sums stay float
    assert (manifest["detector"]["operator_precision"]["Conv"].get("int8", 0) > 0) == detector_int8


def test_int8_engine_agrees_with_float_on_roi_labels_and_objects(int8_export):
    float_dir, int8_dir = int8_export
    reference = load_erasenet(DETECTOR, SEGMENTER, runtime="onnx", onnx_dir=float_dir)
    int8 = load_erasenet(DETECTOR, SEGMENTER, runtime="onnx-int8", onnx_dir=int8_dir)
    assert reference.runtime == "onnx" and int8.runtime == "onnx-int8"
    for frame in simulate_sequence("small", 2, seed=2026, sequence_index=3):
        want = reference.segment(frame.cube)
        assert len(want.regions) > 0
        # the segmenter graph on the same ROI (the float pipeline's seeds): the labels of its voxels
        same_seeds = int8.segment(frame.cube, centres=want.centres)
        assert same_seeds.compute.runtime == "onnx-int8"
        np.testing.assert_array_equal(same_seeds.regions.voxels, want.regions.voxels)
        roi = tuple(want.regions.voxels.T)
        assert (same_seeds.labels[roi] == want.labels[roi]).mean() >= 0.99
        # both graphs end to end: the same objects
        have = int8.segment(frame.cube)
        assert sorted(o.class_id for o in have.objects) == sorted(o.class_id for o in want.objects)


def test_documented_example_runs_the_int8_graphs_without_torch(int8_export, tmp_path):
    """docs/onnx_example.py (numpy and onnxruntime only) on the int8 export labels the ROI as the onnx-int8 engine."""
    from tests.models.export.test_onnx_export import run_documented_example

    _, int8_dir = int8_export
    engine = load_erasenet(DETECTOR, SEGMENTER, runtime="onnx-int8", onnx_dir=int8_dir)
    frame = next(simulate_sequence(engine.profile.name, 1, seed=7))
    labels = run_documented_example(int8_dir, frame.cube, tmp_path)
    expected = engine.segment(frame.cube)
    roi = tuple(expected.regions.voxels.T)
    assert len(expected.regions) > 0 and (labels[roi] == expected.labels[roi]).mean() >= 0.99


def test_an_onnx_dir_of_the_other_precision_is_refused(int8_export):
    float_dir, int8_dir = int8_export
    with pytest.raises(ValueError, match="int8 export, but float32"):
        load_erasenet(DETECTOR, SEGMENTER, runtime="onnx", onnx_dir=int8_dir)
    with pytest.raises(ValueError, match="float32 export, but int8"):
        load_erasenet(DETECTOR, SEGMENTER, runtime="onnx-int8", onnx_dir=float_dir)


def test_roi_label_agreement_counts_voxels_labelled_by_either():
    reference = np.array([[0, 1, 1, 2]])
    assert roi_label_agreement([reference], [reference]) == 1.0
    assert roi_label_agreement([reference], [np.array([[3, 1, 0, 2]])]) == pytest.approx(2 / 4)


def test_export_cache_keys_on_checkpoints_and_calibration(tiny_checkpoints, tmp_path):
    det, seg = load_pair(*tiny_checkpoints)
    cubes, description = simulated_calibration_frames("small", 2)
    seeds = {"score_threshold": 0.0, "max_objects": 1}  # the untrained tiny detector: its best cell
    first = Int8Calibration(tuple(cubes[:1]), description, ("MinMax",)).with_pipeline(**seeds)
    other = Int8Calibration(tuple(cubes[1:]), description, ("MinMax",)).with_pipeline(**seeds)
    one = exported_dir(det, seg, tmp_path, int8=first)
    assert exported_dir(det, seg, tmp_path, int8=first) == one  # cached
    assert exported_dir(det, seg, tmp_path, int8=other) != one  # other frames, another export
    assert exported_dir(det, seg, tmp_path, int8=first.with_pipeline(score_threshold=0.0, max_objects=2)) != one
    plain = exported_dir(det, seg, tmp_path)
    assert plain not in (one,) and json.loads((plain / "manifest.json").read_text()).get("precision") is None
    assert exported_dir(*load_pair(*tiny_checkpoints), tmp_path) == plain  # the files loaded again: the same key
    assert json.loads((one / "manifest.json").read_text())["precision"] == "int8"
