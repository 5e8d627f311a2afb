"""int8 ERASE-Net: both exported graphs statically quantised with onnxruntime, calibrated on radar frames.

``detector.onnx`` and ``segmenter.onnx`` of a float export (:mod:`models.export.onnx_export`) go through
``onnxruntime.quantization.quantize_static``: QDQ format (standard QuantizeLinear / DequantizeLinear around the
float operators, so the files stay standard ONNX), weights signed int8 per output channel, activations 8-bit,
ranges calibrated on frames:

- the detector on the frames' log power (R, A, D) dB;
- the segmenter on what the float pipeline feeds it on those frames: the features of the ROI voxels region
  growing gives around the float detector's centres, and their kernel maps (captured from the float engine).

Calibration frames come from the train split of a preprocessed store (read by
:mod:`pipelines.datasets.calibration`, which hands the cubes in), or, when none is given, from the project's
simulator (a few frames of the model's preset at :data:`SIMULATED_SEED`): the embedded data source, so the
service can build the int8 graphs from the checkpoints alone. The manifest says which.

The calibration method (MinMax, Entropy, Percentile) is chosen per export by measurement: each one quantises
both graphs, and the one whose int8 pipeline gives the float pipeline's label on the most ROI voxels of the
calibration frames wins; every method's agreement is recorded in the manifest. The manifest also gives, per
graph and operator type, how many nodes run on 8-bit data and how many stay float or are index arithmetic.

Activations are unsigned 8-bit (asymmetric), not signed: onnxruntime converts signed activations of a MatMul to
unsigned on x86, which leaves a DequantizeLinear -> Gather -> QuantizeLinear pair around every gather (float
gathers plus two conversions); measured on the shipped segmenter, one frame of 22 k ROI voxels, one thread:
float graph 61.5 ms, signed activations 94.2 ms, unsigned 59.5 ms (gathers in 8 bits, no conversion left).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from models.checkpoint import Checkpoint

log = logging.getLogger(__name__)

QUANT_VERSION = 1
"""Bump when the quantisation recipe changes: the int8 export cache keys on it."""
METHODS = ("MinMax", "Entropy", "Percentile")
CALIBRATION_FRAMES = 8
"""Default calibration frames (each frame's ROI gives the segmenter tens of thousands of voxel rows)."""
SIMULATED_SEED = 7_204_311
"""Scene seed of the simulated calibration frames (apart from the seeds tests and benchmarks draw)."""
SIMULATED_SEQUENCES = 2
QUANTISED_FILES = ("detector.onnx", "segmenter.onnx")


def simulated_calibration_frames(preset: Any, frames: int, *, seed: int = SIMULATED_SEED
                                 ) -> tuple[list[np.ndarray], dict[str, Any]]:
    """``frames`` log-power cubes of the preset from the project's simulator (``SIMULATED_SEQUENCES`` sequences)."""
    from radar import transforms
    from radar.simulate import simulate_sequence

    if frames < 1:
        raise ValueError(f"calibration frames must be >= 1, got {frames}")
    per_sequence = -(-frames // SIMULATED_SEQUENCES)
    cubes: list[np.ndarray] = []
    for sequence in range(SIMULATED_SEQUENCES):
        for frame in simulate_sequence(preset, per_sequence, seed=seed, sequence_index=sequence):
            cubes.append(transforms.log_power(frame.cube))
    cubes = cubes[:frames]
    name = getattr(preset, "name", preset)
    return cubes, {"source": "simulated", "preset": str(name), "seed": seed, "sequences": SIMULATED_SEQUENCES,
                   "frames": len(cubes), "note": "no store given: frames of the model's preset from radar.simulate"}


def calibration_digest(cubes: Sequence[np.ndarray]) -> str:
    """sha256 of the calibration frames' bytes: the int8 export cache keys on it with the checkpoints."""
    digest = hashlib.sha256()
    for cube in cubes:
        digest.update(np.ascontiguousarray(cube, dtype=np.float32).tobytes())
    return digest.hexdigest()


class _Feeds:
    """onnxruntime's ``CalibrationDataReader`` over a list of input dicts (duck-typed), read in ranges.

    ``quantize_static`` with ``CalibStridedMinMax = 1`` collects one input at a time through ``set_range``: the
    histogram calibrators (Entropy, Percentile) stack each tensor's values over the inputs they collect at once,
    which fails when the segmenter's voxel counts differ between frames."""

    def __init__(self, feeds: Sequence[dict[str, np.ndarray]]) -> None:
        self._all = list(feeds)
        self._feeds: Iterator[dict[str, np.ndarray]] = iter(self._all)

    def __len__(self) -> int:
        return len(self._all)

    def set_range(self, start_index: int, end_index: int) -> None:
        self._feeds = iter(self._all[start_index:end_index])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def float_pipeline_feeds(float_dir: Path, detector: Checkpoint, segmenter: Checkpoint, cubes: Sequence[np.ndarray],
                         pipeline: dict[str, Any] | None = None
                         ) -> tuple[list[dict[str, np.ndarray]], list[dict[str, np.ndarray]], list[np.ndarray]]:
    """Run the float graphs on the frames (``pipeline``: EraseNet keyword arguments, e.g. the model's
    ``score_threshold``) and capture each graph's inputs.

    Returns:
        (detector feeds, segmenter feeds, float labels of each frame's ROI voxels): the segmenter's feeds are its
        features and kernel maps on the ROI of each frame (frames with an empty ROI give none).
    """
    from models.export.kernel_maps_numpy import kernel_maps
    from models.export.onnx_engine import OnnxEraseNet

    net = OnnxEraseNet.from_checkpoints(detector, segmenter, onnx_dir=float_dir, threads=1, **(pipeline or {}))
    captured: list[dict[str, np.ndarray]] = []
    run_segmenter = net.voxel_logits

    def capture(coords: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
        captured.append({"features": features, **kernel_maps(coords)})
        return run_segmenter(coords, features)

    net.voxel_logits = capture  # type: ignore[method-assign]
    labels = []
    for cube in cubes:
        result = net.segment(cube, is_log_power=True)
        labels.append(result.labels)
    return [{"log_power": np.ascontiguousarray(c, dtype=np.float32)} for c in cubes], captured, labels


def quantise_graph(source: Path, target: Path, feeds: Sequence[dict[str, np.ndarray]], method: str) -> None:
    """``quantize_static`` of one graph: QDQ, weights int8 per channel, activations uint8, ``method`` ranges."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    if method not in METHODS:
        raise ValueError(f"calibration method must be one of {METHODS}, got {method!r}")
    with tempfile.TemporaryDirectory(prefix="calibrate-") as scratch:
        cwd = os.getcwd()
        os.chdir(scratch)  # the calibrator writes its augmented model into the working directory
        try:
            quantize_static(str(source), str(target), _Feeds(feeds), quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            calibrate_method=getattr(CalibrationMethod, method),
                            extra_options={"CalibStridedMinMax": 1})
        finally:
            os.chdir(cwd)


def operator_precision(path: Path) -> dict[str, dict[str, int]]:
    """Per operator type of a QDQ graph, how many nodes compute on 8-bit data and how many do not.

    A node is ``int8`` when one of its inputs comes from a DequantizeLinear (onnxruntime fuses the pair into an
    8-bit kernel, or drops it around a data-movement op such as Gather, Reshape, Slice, Concat); ``float`` when
    it takes float data from elsewhere; ``index`` when it only handles integers (shapes, kernel-map rows).
    QuantizeLinear / DequantizeLinear themselves and Constants are not counted.
    """
    import onnx

    model = onnx.shape_inference.infer_shapes(onnx.load(str(path)))
    types = {v.name: v.type.tensor_type.elem_type for v in (*model.graph.value_info, *model.graph.input,
                                                             *model.graph.output)}
    types.update({i.name: i.data_type for i in model.graph.initializer})
    produced_by = {out: node.op_type for node in model.graph.node for out in node.output}
    floats = {onnx.TensorProto.FLOAT, onnx.TensorProto.FLOAT16}
    table: dict[str, Counter] = {}
    for node in model.graph.node:
        if node.op_type in ("QuantizeLinear", "DequantizeLinear", "Constant"):
            continue
        inputs = [name for name in node.input if name]
        if any(produced_by.get(name) == "DequantizeLinear" for name in inputs):
            kind = "int8"
        elif any(types.get(name) in floats for name in inputs):
            kind = "float"
        else:
            kind = "index"
        table.setdefault(node.op_type, Counter())[kind] += 1
    return {op: dict(sorted(counts.items())) for op, counts in sorted(table.items())}


def roi_label_agreement(float_labels: Sequence[np.ndarray], int8_labels: Sequence[np.ndarray]) -> float:
    """Share of the float pipeline's ROI voxels (non-background in either) where both pipelines give one label."""
    same = total = 0
    for reference, got in zip(float_labels, int8_labels, strict=True):
        voxels = (reference > 0) | (got > 0)
        same += int(np.count_nonzero(reference[voxels] == got[voxels]))
        total += int(np.count_nonzero(voxels))
    return same / total if total else 1.0


def export_int8(detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint, out: str | Path, *,
                cubes: Sequence[np.ndarray], calibration: dict[str, Any], methods: Sequence[str] = METHODS,
                float_dir: str | Path | None = None, pipeline: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write the int8 graphs and their manifest into ``out``.

    Args:
        cubes: calibration frames, log power (R, A, D) dB (``store_calibration_frames``,
            ``simulated_calibration_frames``); calibration: their description, written into the manifest.
        methods: calibration methods to try; the one with the best ROI label agreement is kept.
        float_dir: an existing float export of these checkpoints (default: exported now into ``out/float``).
        pipeline: EraseNet keyword arguments of the float and int8 pipelines compared (``score_threshold``,
            ``max_objects``; default EraseNet's).

    Returns:
        The manifest (written last: a directory with a manifest is complete).
    """
    from models.erasenet.model import EraseNet
    from models.export.onnx_engine import OnnxEraseNet
    from models.export.onnx_export import export_onnx

    if not methods:
        raise ValueError("give at least one calibration method")
    det, seg = EraseNet.load_pair(detector, segmenter)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").unlink(missing_ok=True)
    if float_dir is None:
        float_dir = out / "float"
        export_onnx(det, seg, float_dir)
    float_dir = Path(float_dir)
    if len(cubes) == 0:
        raise ValueError("no calibration frames")
    det_feeds, seg_feeds, float_labels = float_pipeline_feeds(float_dir, det, seg, cubes, pipeline)
    if not seg_feeds:
        raise ValueError("no calibration frame has ROI voxels: the segmenter cannot be calibrated on them")
    float_manifest = json.loads((float_dir / "manifest.json").read_text())
    agreement: dict[str, float] = {}
    best: str | None = None
    for method in methods:
        trial = out / f".{method}"
        trial.mkdir(exist_ok=True)
        for name, feeds in (("detector.onnx", det_feeds), ("segmenter.onnx", seg_feeds)):
            log.info("quantising %s (%s, %d calibration inputs)", name, method, len(feeds))
            quantise_graph(float_dir / name, trial / name, feeds, method)
        (trial / "manifest.json").write_text(json.dumps({**float_manifest, "precision": "int8"}))
        net = OnnxEraseNet.from_checkpoints(det, seg, onnx_dir=trial, threads=1, int8=True, **(pipeline or {}))
        int8_labels = [net.segment(cube, is_log_power=True).labels for cube in cubes]
        agreement[method] = roi_label_agreement(float_labels, int8_labels)
        log.info("%s: ROI label agreement with float %.5f", method, agreement[method])
        if best is None or agreement[method] > agreement[best]:
            best = method
    assert best is not None
    for name in QUANTISED_FILES:
        os.replace(out / f".{best}" / name, out / name)
    for method in methods:
        shutil.rmtree(out / f".{method}", ignore_errors=True)
    manifest = dict(float_manifest)
    manifest["precision"] = "int8"
    for stage, name in (("detector", "detector.onnx"), ("segmenter", "segmenter.onnx")):
        graph = dict(float_manifest[stage])
        graph["operators"] = sorted(set(graph["operators"]) | {"QuantizeLinear", "DequantizeLinear"})
        graph["float_bytes"] = (float_dir / name).stat().st_size
        graph["bytes"] = (out / name).stat().st_size
        graph["operator_precision"] = operator_precision(out / name)
        manifest[stage] = graph
    manifest["quantization"] = {
        "version": QUANT_VERSION, "tool": "onnxruntime.quantization.quantize_static", "format": "QDQ",
        "weights": "int8, symmetric, per output channel", "activations": "uint8, asymmetric, per tensor",
        "method": best, "label_agreement_by_method": agreement,
        "agreement_measure": "share of the ROI voxels (non-background in float or int8) with the same label, "
                             "int8 pipeline against float, on the calibration frames",
        "calibration": {**calibration, "sha256": calibration_digest(cubes), "segmenter_inputs": len(seg_feeds),
                        "pipeline": pipeline or "EraseNet defaults"},
        "float_export": {"format": float_manifest["format"], "version": float_manifest["version"]},
    }
    tmp = out / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2))
    os.replace(tmp, out / "manifest.json")
    return manifest
