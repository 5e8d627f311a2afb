"""int8 ERASE-Net: the exported graphs statically quantised with onnxruntime, calibrated on radar frames.

``detector.onnx`` and ``segmenter.onnx`` of a float export (:mod:`models.export.onnx_export`) go through
``onnxruntime.quantization.quantize_static``: QDQ format (standard QuantizeLinear / DequantizeLinear around the
float operators, so the files stay standard ONNX), weights signed int8 per output channel (on 7 bits, so that no
CPU's kernels overflow: ``QUANT_VERSION`` 7), activations 8-bit,
ranges calibrated on frames:

- the detector on the frames' log power (R, A, D) dB, and a detector that reads earlier frames on the frames
  before each in the list (:func:`calibration_history`; the first frame's absent), as the float pipeline feeds it;
- the segmenter on what the float pipeline feeds it on those frames: the features of the ROI voxels region
  growing gives around the float detector's centres, and their kernel maps (captured from the float engine).

What stays float is chosen by measurement, one thread:

- the detector graph is timed float, int8 and float compute on int8 weights on the calibration frames,
  interleaved, and it computes in int8 only when that is faster than the int8-weights graph, the one that ships
  otherwise (measured on the shipped pair, AVX-512 VNNI CPU, onnxruntime 1.32: float 3.7-3.8 ms, int8 4.8-4.9 ms:
  the small convolutions pay more for the QDQ conversions than they gain). int8 compute costs detection accuracy
  (0.0095-0.0112 mAP on 192 fresh frames in three exports; int8 weights 0.001), so a tie or a gain within timing
  noise must not buy it: one export had chosen it against float by 0.09 ms while the int8-weights graph ran 0.003 ms
  faster still. The manifest gives each graph's ``precision`` and the three timings;
- in the segmenter, ``Add`` (since export format 3 only the residual sums: each bias is its Gemm's C input, which
  quantises to one QGemm with an int32 bias) is not quantised (:data:`NOT_QUANTIZED`). With the biases as Adds, a
  QLinearAdd per sum cost more than the float Add (shipped segmenter, 6 calibration frames of 12-49 k voxels,
  median of each frame's best: float 42-46 ms, every op int8 31-34 ms, all but Add 29-32 ms; voxel label agreement
  with float 99.8 %); with the 16 residual sums alone, QLinearAdd was within 2 % (46.5 against 47.2 ms on 8
  frames of 14-42 k voxels, a training job on the other core): kept float.

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
from models.export.compact import int8_weights, short_names
from models.export.label_agreement import roi_label_agreement  # float against int8 ROI labels
from models.export.onnx_engine import INT8_WEIGHTS
from radar.input_kind import InputKind

log = logging.getLogger(__name__)

QUANT_VERSION = 7
"""Bump when the quantisation recipe changes: the int8 export cache keys on it (4: the segmenter quantised from
its z-column form, :func:`_column_segmenter`; 5: the detector computes in int8 only where it beats the int8-weights
graph, not the float one; 6: a detector that reads earlier frames calibrated with them; 7: weights on 7 bits,
``reduce_range``: onnxruntime's uint8 x int8 kernels on a CPU without VNNI add pairs of products in 16 bits, which
8-bit weights can overflow; on an AVX2-only CPU the int8 detector then found other objects than the float one)."""
METHODS = ("MinMax", "Entropy", "Percentile")
CALIBRATION_FRAMES = 8
"""Default calibration frames (each frame's ROI gives the segmenter tens of thousands of voxel rows)."""
SIMULATED_SEED = 7_204_311
"""Scene seed of the simulated calibration frames (apart from the seeds tests and benchmarks draw)."""
SIMULATED_SEQUENCES = 2
QUANTIZED_FILES = ("detector.onnx", "segmenter.onnx")
NOT_QUANTIZED = {"detector.onnx": (), "segmenter.onnx": ("Add",)}
"""Operator types each graph keeps in float (measured slower in 8 bits; see the module's docstring)."""
DETECTOR_TIMING_ROUNDS = 5


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
    return cubes, simulated_calibration_description(preset, len(cubes), seed=seed)


def simulated_calibration_description(preset: Any, frames: int, *, seed: int = SIMULATED_SEED) -> dict[str, Any]:
    """What :func:`simulated_calibration_frames` says of its ``frames`` frames (the manifest's description; the
    int8 calibration cache keys on it without simulating them)."""
    return {"source": "simulated", "preset": str(getattr(preset, "name", preset)), "seed": seed,
            "sequences": SIMULATED_SEQUENCES, "frames": frames,
            "note": "no store given: frames of the model's preset from radar.simulate"}


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


def calibration_history(cubes: Sequence[np.ndarray], index: int, history_frames: int) -> list[np.ndarray | None] | None:
    """The earlier frames frame ``index`` of the calibration list reads: the ones before it in the list, the latest
    first, None before the first (calibration frames come in sequences); None for a detector of one frame."""
    if not history_frames:
        return None
    return [cubes[index - 1 - h] if index - 1 - h >= 0 else None for h in range(history_frames)]


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

    detector_feeds: list[dict[str, np.ndarray]] = []
    run_feed = net._run_detector.feed

    def capture_feed(*args: np.ndarray | None) -> dict[str, np.ndarray]:
        detector_feeds.append(run_feed(*args))
        return detector_feeds[-1]

    net.voxel_logits = capture  # type: ignore[method-assign]
    net._run_detector.feed = capture_feed  # type: ignore[method-assign]
    labels = []
    for index, cube in enumerate(cubes):
        history = calibration_history(cubes, index, net.history_frames)
        result = net.segment(cube, kind=InputKind.log_power, history=history)
        labels.append(result.labels)
    return detector_feeds, captured, labels


def quantize_graph(source: Path, target: Path, feeds: Sequence[dict[str, np.ndarray]], method: str,
                   not_quantized: Sequence[str] = ()) -> None:
    """``quantize_static`` of one graph: QDQ, weights int8 per channel, activations uint8, ``method`` ranges;
    the operator types in ``not_quantized`` stay float."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    if method not in METHODS:
        raise ValueError(f"calibration method must be one of {METHODS}, got {method!r}")
    op_types = None
    if not_quantized:
        op_types = sorted({node.op_type for node in onnx.load(str(source)).graph.node} - set(not_quantized))
    source, target = Path(source).absolute(), Path(target).absolute()  # the working directory changes below
    with tempfile.TemporaryDirectory(prefix="calibrate-") as scratch:
        cwd = os.getcwd()
        os.chdir(scratch)  # the calibrator writes its augmented model into the working directory
        try:
            quantize_static(str(source), str(target), _Feeds(feeds), quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                            reduce_range=True,
                            calibrate_method=getattr(CalibrationMethod, method), op_types_to_quantize=op_types,
                            extra_options={"CalibStridedMinMax": 1})
        finally:
            os.chdir(cwd)


def operator_precision(path: Path, not_quantized: Sequence[str] = ()) -> dict[str, dict[str, int]]:
    """Per operator type of a QDQ graph, how many nodes compute on 8-bit data and how many do not.

    A node is ``int8`` when one of its inputs comes from a DequantizeLinear (onnxruntime fuses the pair into an
    8-bit kernel, or drops it around a data-movement op such as Gather, Reshape, Slice, Concat); ``float`` when
    it takes float data from elsewhere; ``index`` when it only handles integers (shapes, kernel-map rows).
    QuantizeLinear / DequantizeLinear themselves and Constants are not counted. Operator types in ``not_quantized``
    (left out of the quantisation) are ``float`` whatever feeds them: their DequantizeLinear inputs stay.
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
        if node.op_type in not_quantized and any(types.get(name) in floats for name in inputs):
            kind = "float"
        elif any(produced_by.get(name) == "DequantizeLinear" for name in inputs):
            kind = "int8"
        elif any(types.get(name) in floats for name in inputs):
            kind = "float"
        else:
            kind = "index"
        table.setdefault(node.op_type, Counter())[kind] += 1
    return {op: dict(sorted(counts.items())) for op, counts in sorted(table.items())}


def time_graphs(paths: dict[str, Path], feeds: Sequence[dict[str, np.ndarray]],
                rounds: int = DETECTOR_TIMING_ROUNDS) -> dict[str, float]:
    """Milliseconds of each graph, one thread: the median over ``feeds`` of each feed's best of ``rounds`` runs, the
    graphs interleaved (order reversed every other round), so a shared machine's load falls on all alike."""
    import time

    from models.export.onnx_engine import _session as session

    sessions = {name: session(path, 1, fold_weights=name == INT8_WEIGHTS) for name, path in paths.items()}
    best = {name: [float("inf")] * len(feeds) for name in sessions}
    for feed in feeds[:1]:
        for run in sessions.values():  # warm-up
            run.run(None, feed)
    for repeat in range(rounds):
        order = list(sessions) if repeat % 2 == 0 else list(sessions)[::-1]
        for index, feed in enumerate(feeds):
            for name in order:
                started = time.perf_counter()
                sessions[name].run(None, feed)
                best[name][index] = min(best[name][index], time.perf_counter() - started)
    return {name: round(1e3 * float(np.median(values)), 3) for name, values in best.items()}


def export_int8(detector: Checkpoint, segmenter: Checkpoint, out: str | Path, *,
                cubes: Sequence[np.ndarray], calibration: dict[str, Any], methods: Sequence[str] = METHODS,
                float_dir: str | Path | None = None, pipeline: dict[str, Any] | None = None,
                int8_detector: bool | None = None) -> dict[str, Any]:
    """Write the int8 graphs and their manifest into ``out``.

    Args:
        cubes: calibration frames, log power (R, A, D) dB (``store_calibration_frames``,
            ``simulated_calibration_frames``); calibration: their description, written into the manifest.
        methods: calibration methods to try; the one with the best ROI label agreement is kept.
        float_dir: an existing float export of these checkpoints (default: exported now into ``out/float``).
        pipeline: EraseNet keyword arguments of the float and int8 pipelines compared (``score_threshold``,
            ``max_objects``; default EraseNet's).
        int8_detector: quantise the detector graph (True), keep float compute on int8 weights (False), or (None,
            the default) compute in int8 only where that runs faster than the int8-weights graph on the calibration
            frames (:func:`time_graphs`).

    Returns:
        The manifest (written last: a directory with a manifest is complete).
    """
    from models.export.onnx_export import export_onnx

    if not methods:
        raise ValueError("give at least one calibration method")
    det, seg = detector, segmenter
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
    feeds = {"detector.onnx": det_feeds, "segmenter.onnx": seg_feeds}
    for method in methods:
        (out / f".{method}").mkdir(exist_ok=True)
    chosen = "given" if int8_detector is not None else "measured"
    int8_detector, detector_ms = _detector_precision(out, float_dir, det_feeds, methods[0], int8_detector)
    sources = {"detector.onnx": float_dir / "detector.onnx", "segmenter.onnx": _column_segmenter(seg, out)}
    _quantize_trials(out, sources, feeds, methods, int8_detector)
    agreement = _agreement_by_method(out, det, seg, cubes, float_labels, float_manifest, methods, pipeline)
    best = max(methods, key=lambda method: agreement[method])  # the first of equals
    for name in QUANTIZED_FILES:  # the chosen graphs, with short internal names (most of a sparse graph's bytes)
        source = out / f".{best}" / name
        if name == "detector.onnx" and not int8_detector:
            source = out / ".detector-int8-weights.onnx"
        short_names(source, out / name)
    for method in methods:
        shutil.rmtree(out / f".{method}", ignore_errors=True)
    (out / ".detector-int8-weights.onnx").unlink(missing_ok=True)
    sources["segmenter.onnx"].unlink(missing_ok=True)
    manifest = _int8_manifest(float_manifest, float_dir, out, int8_detector)
    manifest["quantization"] = {
        "version": QUANT_VERSION, "tool": "onnxruntime.quantization.quantize_static", "format": "QDQ",
        "segmenter_form": "3^3 convs gather z-columns, then 9 columns per voxel (the float graph gathers 27 rows)",
        "weights": "int8, symmetric, per output channel", "activations": "uint8, asymmetric, per tensor",
        "graphs": {"detector": manifest["detector"]["precision"], "segmenter": "int8"},
        "files": "internal tensor names shortened, node names and doc strings dropped (models.export.compact)",
        "not_quantised_op_types": {"detector": list(NOT_QUANTIZED["detector.onnx"]) if int8_detector else "all",
                                   "segmenter": list(NOT_QUANTIZED["segmenter.onnx"])},
        "detector_ms_one_thread": {**detector_ms, "measure": "median over the calibration frames of each one's "
                                   f"best of {DETECTOR_TIMING_ROUNDS}, interleaved", "chosen": chosen},
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


def _detector_precision(out: Path, float_dir: Path, feeds: Sequence[dict[str, np.ndarray]], method: str,
                        int8_detector: bool | None) -> tuple[bool, dict[str, float]]:
    """Whether the detector computes in int8 (as given, or where it runs faster) and the timings: its int8 graph
    (``method``, into ``out/.METHOD``) against the float one and against float compute on int8 weights (what a
    float detector ships as, ``out/.detector-int8-weights.onnx``: a quarter of the bytes, the float speed)."""
    quantize_graph(float_dir / "detector.onnx", out / f".{method}" / "detector.onnx", feeds, method)
    int8_weights(float_dir / "detector.onnx", out / ".detector-int8-weights.onnx")
    detector_ms = time_graphs({"float32": float_dir / "detector.onnx", "int8": out / f".{method}" / "detector.onnx",
                               INT8_WEIGHTS: out / ".detector-int8-weights.onnx"}, feeds)
    if int8_detector is None:
        int8_detector = detector_ms["int8"] < detector_ms[INT8_WEIGHTS]
    log.info("detector graph ms float %.2f, int8 %.2f, int8 weights %.2f: the detector is %s",
             detector_ms["float32"], detector_ms["int8"], detector_ms[INT8_WEIGHTS],
             "int8" if int8_detector else INT8_WEIGHTS)
    return int8_detector, detector_ms


def _column_segmenter(segmenter: Checkpoint, out: Path) -> Path:
    """The float segmenter graph in the form its int8 graph is quantised from: 3^3 convs gathering z-columns
    (``ExportMinkUNet(column_gathers=True)``, the float export's form too). Same inputs and outputs."""
    from models.export.onnx_export import export_segmenter

    path = out / ".segmenter-columns.onnx"
    export_segmenter(segmenter.build().eval(), segmenter.profile, path, column_gathers=True)
    return path


def _quantize_trials(out: Path, sources: dict[str, Path], feeds: dict[str, Sequence[dict[str, np.ndarray]]],
                     methods: Sequence[str], int8_detector: bool) -> None:
    """Each method's graphs, quantised from ``sources`` (float graphs by file name), into ``out/.METHOD`` (the
    first method's int8 detector is there already); the float detector there when ``int8_detector`` is false."""
    for method in methods:
        for name in QUANTIZED_FILES:
            target = out / f".{method}" / name
            if name == "detector.onnx" and not int8_detector:
                shutil.copyfile(sources[name], target)
            elif not (name == "detector.onnx" and method == methods[0]):
                log.info("quantising %s (%s, %d calibration inputs)", name, method, len(feeds[name]))
                quantize_graph(sources[name], target, feeds[name], method, NOT_QUANTIZED[name])


def _agreement_by_method(out: Path, det: Checkpoint, seg: Checkpoint, cubes: Sequence[np.ndarray],
                         float_labels: Sequence[np.ndarray], float_manifest: dict[str, Any], methods: Sequence[str],
                         pipeline: dict[str, Any] | None) -> dict[str, float]:
    """ROI label agreement with float of the int8 pipeline of each method's graphs (in ``out/.METHOD``)."""
    from models.export.onnx_engine import OnnxEraseNet

    agreement: dict[str, float] = {}
    for method in methods:
        trial = out / f".{method}"
        (trial / "manifest.json").write_text(json.dumps({**float_manifest, "precision": "int8"}))
        net = OnnxEraseNet.from_checkpoints(det, seg, onnx_dir=trial, threads=1, int8=True, **(pipeline or {}))
        int8_labels = [net.segment(cube, kind=InputKind.log_power,
                                   history=calibration_history(cubes, index, net.history_frames)).labels
                       for index, cube in enumerate(cubes)]
        agreement[method] = roi_label_agreement(float_labels, int8_labels)
        log.info("%s: ROI label agreement with float %.5f", method, agreement[method])
    return agreement


def _int8_manifest(float_manifest: dict[str, Any], float_dir: Path, out: Path, int8_detector: bool) -> dict[str, Any]:
    """The float manifest with each graph's precision, bytes (and float bytes) and operators' precision."""
    manifest = dict(float_manifest)
    manifest["precision"] = "int8"
    for stage, name in (("detector", "detector.onnx"), ("segmenter", "segmenter.onnx")):
        graph = dict(float_manifest[stage])
        quantised = stage == "segmenter" or int8_detector
        graph["precision"] = "int8" if quantised else INT8_WEIGHTS
        if quantised:
            graph["operators"] = sorted(set(graph["operators"]) | {"QuantizeLinear", "DequantizeLinear"})
        graph["float_bytes"] = (float_dir / name).stat().st_size
        graph["bytes"] = (out / name).stat().st_size
        # what each operator computes in: the float graph's for a detector of int8 weights (folded at load)
        graph["operator_precision"] = (operator_precision(out / name, NOT_QUANTIZED[name]) if quantised
                                       else operator_precision(float_dir / name, ()))
        manifest[stage] = graph
    return manifest
