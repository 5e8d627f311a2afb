"""ONNX export and engine: kernel maps equal the sparse engine's, the ONNX engine segments like the PyTorch one
on fresh frames of every shipped checkpoint pair, and the graphs run with numpy and onnxruntime alone."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from models.checkpoint import load_checkpoint
from models.export.centres_numpy import decode_centres
from models.export.kernel_maps_numpy import STRIDES, expand_neighbours, input_names, kernel_maps
from models.export.sparse_graph import ExportMinkUNet
from models.registry import create_model
from models.runtime import load_erasenet
from models.sparse import SparseTensor
from pipelines.cli import main
from radar import transforms
from radar.roi import roi_points
from radar.simulate import simulate_sequence

ROOT = Path(__file__).resolve().parents[3]
CHECKPOINTS = ROOT / "checkpoints"
# Every shipped pair: the preset each was trained for comes from the checkpoint (all are `small` today).
PAIRS = [pytest.param((CHECKPOINTS / f"detector{suffix}.pt", CHECKPOINTS / f"segmenter{suffix}.pt"),
                      id=suffix.strip("-") or "shipped")
         for suffix in ("", "-p40") if (CHECKPOINTS / f"segmenter{suffix}.pt").is_file()]
FRAMES = 2


def test_numpy_kernel_maps_equal_the_sparse_engines():
    rng = np.random.default_rng(0)
    coords = np.unique(rng.integers(0, 24, size=(900, 3)), axis=0)
    rng.shuffle(coords)  # the caller's order is kept at stride 1
    maps = kernel_maps(coords)
    batch = np.zeros((len(coords), 1), np.int64)
    cache = SparseTensor(torch.from_numpy(np.hstack([batch, coords])), torch.zeros(len(coords), 4)).cache
    for stride in STRIDES:
        table, columns = maps[f"neighbours_s{stride}"], maps[f"columns_s{stride}"]
        assert table.shape == (len(cache.coords(stride)), 9) and len(columns) >= len(table)
        full = expand_neighbours(columns, table)
        assert np.array_equal(full, cache.kernel_map(stride, 3, 1).neighbours.numpy()), stride
    assert len(maps["columns_s1"]) > len(maps["neighbours_s1"])  # empty positions beside voxels have columns too
    for stride in STRIDES[:-1]:
        down = cache.kernel_map(stride, 2, 2)
        assert np.array_equal(maps[f"down_s{stride}"], down.neighbours.numpy())
        assert np.array_equal(maps[f"up_s{stride}"], down.parent_slots.numpy())


def test_compiled_kernel_maps_equal_numpys_on_sorted_voxels():
    """The ONNX engine's maps (the compiled engine's one-pass pyramid) are numpy's tables, entry for entry, on
    sorted voxels (as region growing gives them); unsorted ones fall back to numpy."""
    from models.export.kernel_maps_compiled import compiled_kernel_maps, fastest_kernel_maps
    from models.sparse import compiled

    rng = np.random.default_rng(1)
    coords = np.unique(rng.integers(0, 40, size=(3000, 3)), axis=0)  # np.unique sorts the rows
    want = kernel_maps(coords)
    got = compiled_kernel_maps(coords)
    if not compiled.enabled_on(torch.device("cpu")):
        assert got is None
    else:
        assert got is not None and list(got) == list(want)
        for name in want:
            assert got[name].dtype == np.int64 and np.array_equal(got[name], want[name]), name
    shuffled = coords[rng.permutation(len(coords))]
    assert compiled_kernel_maps(shuffled) is None
    assert all(np.array_equal(fastest_kernel_maps(shuffled)[k], v) for k, v in kernel_maps(shuffled).items())
    with pytest.raises(ValueError, match=">= 0"):
        fastest_kernel_maps(np.array([[1, -2, 3]]))
    with pytest.raises(ValueError, match="integers"):
        fastest_kernel_maps(np.array([[1.5, 2.0, 3.0]]))
    with pytest.raises(ValueError, match="repeated rows"):  # sorted, so the compiled pass sees them first
        fastest_kernel_maps(np.array([[1, 2, 3], [1, 2, 3], [1, 2, 4]]))


def test_column_and_row_gathers_give_the_same_logits():
    """The int8 graph's source (3^3 convs gathering z-columns) and the float graph (27 rows from the table expanded
    in the graph) compute the same function of the same inputs."""
    model = load_checkpoint(PAIRS[0].values[0][1]).build()
    rng = np.random.default_rng(3)
    coords = np.unique(rng.integers(0, 30, size=(2500, 3)), axis=0)
    maps = kernel_maps(coords)
    feats = torch.from_numpy(rng.standard_normal((len(coords), 4)).astype(np.float32))
    inputs = [torch.from_numpy(maps[name]) for name in input_names()]
    with torch.no_grad():
        rows = ExportMinkUNet(model)(feats, *inputs)
        columns = ExportMinkUNet(model, column_gathers=True)(feats, *inputs)
    torch.testing.assert_close(columns, rows, rtol=1e-4, atol=1e-4)


def test_kernel_maps_refuse_bad_coordinates():
    with pytest.raises(ValueError, match="repeated rows"):
        kernel_maps(np.array([[1, 2, 3], [1, 2, 3]]))
    with pytest.raises(ValueError, match=">= 0"):
        kernel_maps(np.array([[1, -2, 3]]))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        kernel_maps(np.zeros((4, 2), np.int64))


def test_export_refuses_spvcnn():
    with pytest.raises(ValueError, match="supports MinkUNet"):
        ExportMinkUNet(create_model("spvcnn_tiny", preset="small").eval())


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    """pair -> (detector, segmenter, export dir), each pair exported once by `radarseg export onnx`."""
    done = {}

    def exported(pair: tuple[Path, Path]) -> tuple[Path, Path, Path]:
        if pair not in done:
            out = tmp_path_factory.mktemp("onnx")
            args = ["export", "onnx", "--detector", str(pair[0]), "--segmenter", str(pair[1]), "--out", str(out)]
            assert main(args) == 0
            done[pair] = (*pair, out)
        return done[pair]

    return exported


@pytest.fixture(scope="module", params=PAIRS)
def exported(request, export):
    """(detector, segmenter, export dir) of every shipped pair."""
    return export(request.param)


@pytest.fixture(scope="module")
def shipped(export):
    """(detector, segmenter, export dir) of the shipped pair only (for checks the slimmed pair adds nothing to)."""
    return export(PAIRS[0].values[0])


def test_export_writes_checked_standard_graphs_and_a_manifest(shipped):
    _, segmenter, out = shipped
    manifest = json.loads((out / "manifest.json").read_text())
    checkpoint = load_checkpoint(segmenter)
    assert manifest["preset"] == checkpoint.preset and manifest["class_names"] == list(checkpoint.class_names)
    assert manifest["opset"] == manifest["detector"]["opset"] == manifest["segmenter"]["opset"]
    assert manifest["detector"]["inputs"]["log_power"]["shape"] == manifest["cube_shape"]
    assert manifest["detector"]["macs"] > 0
    seg = manifest["segmenter"]
    assert list(seg["inputs"]) == ["features", *input_names()]
    assert seg["inputs"]["features"]["shape"] == ["voxels_s1", 4]  # dynamic voxel count
    assert {"Gather", "Gemm"} <= set(seg["operators"]) and not {"ScatterND", "Loop"} & set(seg["operators"])


def test_every_segmenter_product_carries_its_bias(shipped):
    """Each sparse conv, transposed conv and 1x1 conv is one Gemm per row block with its (folded) bias as the C
    input, so the only Adds left are the residual sums: a separate bias Add cost a DequantizeLinear, a float Add
    and a QuantizeLinear per block in the int8 graph."""
    from collections import Counter

    import onnx

    from models.export.sparse_graph import Residual

    _, segmenter, out = shipped
    graph = onnx.shape_inference.infer_shapes(onnx.load(str(out / "segmenter.onnx"))).graph
    ops = Counter(node.op_type for node in graph.node)
    floats = {info.name for info in graph.value_info if info.type.tensor_type.elem_type == onnx.TensorProto.FLOAT}
    float_adds = [node for node in graph.node if node.op_type == "Add" and node.output[0] in floats]
    model = ExportMinkUNet(load_checkpoint(segmenter).build().eval())
    residuals = sum(isinstance(module, Residual) for module in model.modules())
    assert residuals > 0 and len(float_adds) == residuals, ops  # the others are row-block bounds (integers)
    assert "MatMul" not in ops and ops["Gemm"] >= len(model.layer_costs()), ops
    gemm_biases = {node.input[2] for node in graph.node if node.op_type == "Gemm" and len(node.input) == 3}
    assert len(gemm_biases) == len(model.layer_costs())  # one bias per product, shared by its row blocks


def test_the_exported_detector_stores_no_block_of_zeros(shipped):
    """A detector that reads history stores no block of zeros for absent earlier frames (they were 0.8 MB of zeros in
    each detector file when it was exported on its single-cube path): the history is an input."""
    import onnx

    detector, _, out = shipped
    assert load_checkpoint(detector).config.get("history_frames", 0) > 0  # the case this guards
    n_range, n_angle = json.loads((out / "manifest.json").read_text())["cube_shape"][:2]
    graph = onnx.load(str(out / "detector.onnx")).graph
    tensors = [*graph.initializer, *(a.t for node in graph.node if node.op_type == "Constant"
                                     for a in node.attribute if a.t.dims)]
    grids = [list(t.dims) for t in tensors if len(t.dims) == 4 and list(t.dims[-2:]) == [n_range, n_angle]]
    assert grids == [[1, 2, n_range, n_angle]], grids  # only the Cartesian channels have the cube's size


def engines(detector: Path, segmenter: Path, out: Path):
    torch.set_num_threads(1)
    return (load_erasenet(detector, segmenter), load_erasenet(detector, segmenter, runtime="onnx", onnx_dir=out))


def test_onnx_engine_segments_like_the_torch_engine(exported):
    reference, onnx = engines(*exported)
    frames = list(simulate_sequence(reference.profile.name, FRAMES, seed=2026))
    for frame in frames:
        expected, got = reference.segment(frame.cube), onnx.segment(frame.cube)
        assert got.compute.runtime == "onnx" and expected.compute.runtime == "torch"
        np.testing.assert_array_equal(got.regions.voxels, expected.regions.voxels)  # same seeds, same ROI
        roi = tuple(expected.regions.voxels.T)
        assert len(expected.regions) > 0
        assert (got.labels[roi] == expected.labels[roi]).mean() >= 0.999
        assert [(o.class_id, o.n_voxels) for o in got.objects] == [(o.class_id, o.n_voxels) for o in expected.objects]
        assert got.compute.macs_by_stage() == expected.compute.macs_by_stage()  # useful MACs, same pairs
        # logits, on this frame's ROI points
        log_power = transforms.log_power(frame.cube)
        points = roi_points(expected.regions.voxels, log_power, reference.profile, mean_db=reference.mean_db,
                            std_db=reference.std_db)
        coords = torch.from_numpy(np.hstack([np.zeros((len(points), 1), np.int64), points.coords]))
        with torch.no_grad():
            torch_logits = reference.segmenter(SparseTensor(coords, torch.from_numpy(points.features))).numpy()
        onnx_logits = onnx.voxel_logits(points.coords, points.features)[0]
        np.testing.assert_allclose(onnx_logits, torch_logits, atol=1e-4, rtol=0)


def test_numpy_decoding_equals_the_detectors(shipped):
    detector, segmenter, out = shipped
    onnx = load_erasenet(detector, segmenter, runtime="onnx", onnx_dir=out)
    for frame in simulate_sequence(onnx.profile.name, 2, seed=11):
        outputs = onnx._run_detector(transforms.log_power(frame.cube))
        expected = onnx.detector.decode(outputs, k=onnx.max_objects, score_threshold=0.05)[0]
        got = decode_centres(*(outputs[name].numpy() for name in ("heatmap", "offset", "doppler")),
                             k=onnx.max_objects, score_threshold=0.05)
        assert len(expected["score"]) > 0
        for name, values in expected.items():
            np.testing.assert_allclose(got[name], values.numpy(), rtol=0, atol=1e-5)


STANDALONE = """
import importlib.util, json, sys
import numpy as np
import onnxruntime as ort
def load(path):
    spec = importlib.util.spec_from_file_location(path.rsplit("/", 1)[1][:-3], path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
kmaps, centres = load(sys.argv[1] + "/kernel_maps_numpy.py"), load(sys.argv[1] + "/centres_numpy.py")
data = np.load(sys.argv[3])
detector = ort.InferenceSession(sys.argv[2] + "/detector.onnx", providers=["CPUExecutionProvider"])
segmenter = ort.InferenceSession(sys.argv[2] + "/segmenter.onnx", providers=["CPUExecutionProvider"])
feed = {"log_power": data["log_power"]}
if len(detector.get_inputs()) > 1:  # a detector that reads earlier frames: none here (all absent, a single cube)
    n_history = detector.get_inputs()[1].shape[0]
    feed.update(history=np.zeros((n_history, *data["log_power"].shape), np.float32),
                history_present=np.zeros(n_history, np.float32))
heatmap, offset, doppler = detector.run(None, feed)
logits, labels = segmenter.run(None, {"features": data["features"], **kmaps.kernel_maps(data["coords"])})
found = centres.decode_centres(heatmap, offset, doppler, k=32, score_threshold=0.3)
np.savez(sys.argv[4], heatmap=heatmap, logits=logits, labels=labels, **found)
ours = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "models", "radar", "pipelines"))
print(json.dumps(ours))
"""


def test_graphs_run_with_numpy_and_onnxruntime_alone(shipped, tmp_path):
    detector, segmenter, out = shipped
    reference = load_erasenet(detector, segmenter)
    frame = next(simulate_sequence(reference.profile.name, 1, seed=7))
    expected = reference.segment(frame.cube)
    log_power = transforms.log_power(frame.cube)
    points = roi_points(expected.regions.voxels, log_power, reference.profile, mean_db=reference.mean_db,
                        std_db=reference.std_db)
    np.savez(tmp_path / "in.npz", log_power=log_power, features=points.features, coords=points.coords)
    script = tmp_path / "standalone.py"
    script.write_text(STANDALONE)
    modules = ROOT / "models" / "export"
    # -I: isolated mode, neither PYTHONPATH nor the current directory: this package cannot be imported
    run = subprocess.run([sys.executable, "-I", str(script), str(modules), str(out), str(tmp_path / "in.npz"),
                          str(tmp_path / "out.npz")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout) == []  # nothing of torch or this package was imported
    result = np.load(tmp_path / "out.npz")
    with torch.no_grad():
        torch_heatmap = reference.detector(reference._detector_input(log_power))["heatmap"].numpy()
    np.testing.assert_allclose(result["heatmap"], torch_heatmap, atol=1e-4)
    roi = tuple(expected.regions.voxels.T)
    assert (result["labels"] == expected.labels[roi]).mean() >= 0.999
    assert len(expected.centres) > 0  # the same seeds (Doppler is refined from the cube afterwards)
    np.testing.assert_allclose(result["score"], expected.centres.score, atol=1e-4)
    np.testing.assert_allclose(result["range_bin"], expected.centres.range_bin, atol=1e-3)


def run_documented_example(onnx_dir: Path, cube: np.ndarray, tmp_path: Path, earlier: list[Path] = ()) -> np.ndarray:
    """docs/onnx_example.py on ``cube`` (and the ``earlier`` cubes' files) in a fresh interpreter (``-I``): the
    labels it writes, after checking that it ran and imported neither torch nor this package."""
    np.save(tmp_path / "cube.npy", cube)
    run = subprocess.run([sys.executable, "-I", str(ROOT / "docs" / "onnx_example.py"), str(onnx_dir),
                          str(tmp_path / "cube.npy"), str(tmp_path / "labels.npy"), *map(str, earlier)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "imported: none" in run.stdout
    return np.load(tmp_path / "labels.npy")


def test_documented_example_segments_like_the_engine_without_torch(shipped, tmp_path):
    detector, segmenter, out = shipped
    reference = load_erasenet(detector, segmenter)
    frame = next(simulate_sequence(reference.profile.name, 1, seed=7))
    labels = run_documented_example(out, frame.cube, tmp_path)
    expected = reference.segment(frame.cube)
    roi = tuple(expected.regions.voxels.T)
    assert len(expected.regions) > 0 and (labels[roi] == expected.labels[roi]).mean() >= 0.999
    outside = np.ones(labels.shape, bool)
    outside[roi] = False
    assert not labels[outside].any()  # the same regions: background everywhere else
