"""Export ERASE-Net's two stages to ONNX with standard operators only, and describe them in a manifest.

``detector.onnx``: log power (R, A, D) in dB -> ``heatmap`` (1, 1, H, W) probabilities, ``offset`` (1, 2, H, W)
cells (range, angle) and ``doppler`` (1, 1, H, W) bins on the stride-4 grid (H = ceil(R / 4), W = ceil(A / 4));
the input normalisation ``(lp - mean) / std`` and the (R, A, D) -> (1, D, R, A) transpose are inside the graph,
BatchNorms folded into the convs. Fixed input shape (the preset's cube). A detector that reads earlier frames
(``history_frames`` H > 0) takes them as two more inputs: ``history`` (H, R, A, D) float32, their log power in dB,
the latest first (normalised inside the graph like ``log_power``), and ``history_present`` (H,) float32, 1 where
that frame exists and 0 where it does not (its ``history`` slice is then ignored: zeros will do); all H absent is
the single-cube path, the same outputs as the PyTorch detector given no history.

``segmenter.onnx``: ROI voxel ``features`` (N, 4) and the kernel maps of their coordinates
(:mod:`models.export.kernel_maps_numpy`) -> ``logits`` (N, num_classes) and ``labels`` (N,) int64; every
voxel count dynamic. See :mod:`models.export.sparse_graph` for the formulation.

Both are traced with the TorchScript-based ``torch.onnx.export`` (the dynamo exporter needs onnxscript) at
:data:`OPSET`, then checked with ``onnx.checker`` (full check: types and shapes inferred) and for operators
outside the standard domain. ``manifest.json`` says what they take and give.
"""

from __future__ import annotations

import copy
import hashlib
import io
import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from models.checkpoint import Checkpoint
from models.compute import ComputeCounter, count_params
from models.detector.inference import fold_batch_norms
from models.export.kernel_maps_numpy import input_names as map_input_names
from models.export.kernel_maps_numpy import kernel_maps
from models.export.sparse_graph import ExportMinkUNet
from radar.profiles import RadarProfile, describe_for_storage
from radar.roi import N_FEATURES

OPSET = 17
"""ONNX opset of both graphs (onnxruntime >= 1.14, OpenVINO, TensorRT 8.6 read it)."""
FORMAT = "radarseg.onnx"
VERSION = 6
"""Bump when the graphs' inputs, outputs or formulation change: the export cache keys on it (2: row blocks
as Slice, not SplitToSequence; 3: each sparse conv's bias is its Gemm's C input, not an Add; 4: the 3^3 maps as
z-columns, ``columns_s*`` inputs; 5: a detector that reads earlier frames takes ``history`` and
``history_present``; 6: the float segmenter's 3^3 convs gather z-columns, as the int8 one's, instead of 27 rows)."""
DETECTOR_OUTPUTS = ("heatmap", "offset", "doppler")
HISTORY_INPUTS = ("history", "history_present")
SEGMENTER_OUTPUTS = ("logits", "labels")
STANDARD_DOMAINS = ("", "ai.onnx")


class ExportError(RuntimeError):
    """An exported graph that fails validation (checker, custom operators)."""


class DetectorGraph(nn.Module):
    """The detector as exported: raw log power (R, A, D) dB -> heatmap, offset, Doppler (BatchNorms folded)."""

    def __init__(self, detector: nn.Module, mean_db: float, std_db: float) -> None:
        super().__init__()
        self.detector = copy.deepcopy(detector).cpu().eval()
        fold_batch_norms(self.detector)
        self.mean_db, self.inv_std = float(mean_db), 1.0 / float(std_db)

    def forward(self, log_power: Tensor, history: Tensor | None = None,
                history_present: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        x = ((log_power - self.mean_db) * self.inv_std).permute(2, 0, 1)[None]  # (1, D, R, A), as EraseNet's
        if history is None:
            outputs = self.detector(x)
        else:  # (H, R, A, D) dB -> (1, H, D, R, A) normalised; an absent frame's channels are zeroed by its presence
            earlier = ((history - self.mean_db) * self.inv_std).permute(0, 3, 1, 2)[None]
            outputs = self.detector(x, earlier, history_present[None])
        return tuple(outputs[name] for name in DETECTOR_OUTPUTS)


class SegmenterGraph(nn.Module):
    """The segmenter as exported: features and kernel maps -> logits and labels."""

    def __init__(self, segmenter: nn.Module, *, column_gathers: bool = False) -> None:
        super().__init__()
        self.net = ExportMinkUNet(segmenter, column_gathers=column_gathers)

    def forward(self, feats: Tensor, *maps: Tensor) -> tuple[Tensor, Tensor]:
        logits = self.net(feats, *maps)
        return logits, logits.argmax(dim=1)


def _trace_to_onnx(module: nn.Module, args: tuple[Tensor, ...], path: Path, input_names: list[str],
                   output_names: list[str], dynamic_axes: dict[str, dict[int, str]] | None = None) -> None:
    with torch.no_grad(), warnings.catch_warnings():
        # The legacy exporter is deprecated in favour of the dynamo one, which needs onnxscript; shape checks
        # in the detector become constants of the trace (its input shape is fixed).
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", UserWarning)
        torch.onnx.export(module, args, str(path), input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes, opset_version=OPSET, do_constant_folding=True, dynamo=False)


def validate(path: Path) -> dict[str, Any]:
    """Check an exported graph with ``onnx.checker`` (full: types and shapes) and for non-standard operators.

    Returns:
        ``{"inputs": {name: shape}, "outputs": {name: shape}, "operators": sorted op types}``, a dimension
        given as its symbolic name when dynamic.

    Raises:
        ExportError: the checker fails or an operator is outside the standard ONNX domain.
    """
    import onnx

    model = onnx.load(str(path))
    try:
        onnx.checker.check_model(model, full_check=True)
    except onnx.checker.ValidationError as exc:
        raise ExportError(f"{path}: not a valid ONNX model ({exc})") from None
    custom = sorted({f"{node.domain}::{node.op_type}" for node in model.graph.node
                     if node.domain not in STANDARD_DOMAINS})
    if custom:
        raise ExportError(f"{path}: operators outside the standard ONNX domain: {custom}")

    def shapes(values) -> dict[str, dict[str, Any]]:
        described = {}
        for value in values:
            tensor = value.type.tensor_type
            dims = [d.dim_param if d.dim_param else d.dim_value for d in tensor.shape.dim]
            dtype = onnx.helper.tensor_dtype_to_np_dtype(tensor.elem_type).name
            described[value.name] = {"shape": dims, "dtype": dtype}
        return described

    return {"inputs": shapes(model.graph.input), "outputs": shapes(model.graph.output),
            "operators": sorted({node.op_type for node in model.graph.node}),
            "opset": max(o.version for o in model.opset_import if o.domain in STANDARD_DOMAINS)}


def export_detector(detector: nn.Module, profile: RadarProfile, mean_db: float, std_db: float, path: Path) -> None:
    """Write ``detector.onnx`` (see the module docstring): with ``history`` inputs for a detector that reads
    earlier frames."""
    example = torch.full(profile.shape, float(mean_db))
    n_history = detector_history_frames(detector)
    args, names = (example,), ["log_power"]
    if n_history:
        args = (example, torch.full((n_history, *profile.shape), float(mean_db)), torch.ones(n_history))
        names = ["log_power", *HISTORY_INPUTS]
    _trace_to_onnx(DetectorGraph(detector, mean_db, std_db), args, path, names, list(DETECTOR_OUTPUTS))


def detector_history_frames(detector: nn.Module) -> int:
    """Earlier frames the detector reads beside the cube (0: one frame)."""
    return int(getattr(detector, "history_frames", 0) or 0)


def example_voxels(profile: RadarProfile) -> np.ndarray:
    """A small blob of voxels (about 300) inside the preset's cube: only the trace's example, any set works."""
    grid = np.stack(np.meshgrid(*(np.arange(min(8, n)) for n in profile.shape), indexing="ij"), axis=-1)
    voxels = grid.reshape(-1, 3)
    keep = np.linalg.norm(voxels - voxels.mean(axis=0), axis=1) <= 4.5
    return voxels[keep] + np.array(profile.shape) // 4


def export_segmenter(segmenter: nn.Module, profile: RadarProfile, path: Path, *,
                     column_gathers: bool = False) -> list[dict[str, Any]]:
    """Write ``segmenter.onnx`` (see the module docstring); returns its layer table for MAC counts.
    ``column_gathers``: the form :func:`export_onnx` writes and int8 is quantised from (3^3 convs gather z-columns,
    :class:`models.export.sparse_graph.ExportMinkUNet`); without it, 27 rows per voxel."""
    graph = SegmenterGraph(segmenter, column_gathers=column_gathers).eval()
    maps = kernel_maps(example_voxels(profile))
    names = map_input_names()
    feats = torch.zeros(len(maps["neighbours_s1"]), N_FEATURES)
    dynamic = {"features": {0: "voxels_s1"}, "logits": {0: "voxels_s1"}, "labels": {0: "voxels_s1"}}
    for name in names:
        stride = int(name.rsplit("_s", 1)[1])
        rows = {"down": f"voxels_s{2 * stride}", "columns": f"columns_s{stride}"}.get(name.split("_")[0],
                                                                                   f"voxels_s{stride}")
        dynamic[name] = {0: rows}
    _trace_to_onnx(graph, (feats, *(torch.from_numpy(maps[n]) for n in names)), path, ["features", *names],
                   list(SEGMENTER_OUTPUTS), dynamic)
    return [cost.to_dict() for cost in graph.net.layer_costs()]


def checkpoint_digest(checkpoint: Checkpoint) -> str:
    """sha256 of a checkpoint's serialised form (what :func:`models.checkpoint.save_checkpoint` writes): the same for
    the object and for the file it was loaded from or is saved to."""
    buffer = io.BytesIO()
    torch.save(checkpoint.to_dict(), buffer)
    return hashlib.sha256(buffer.getvalue()).hexdigest()


def export_onnx(detector: Checkpoint, segmenter: Checkpoint, out: str | Path) -> dict[str, Any]:
    """Export both stages into ``out`` (``detector.onnx``, ``segmenter.onnx``, ``manifest.json``).

    Returns:
        The manifest (also written to ``out/manifest.json``, last, so a directory with a manifest is complete).

    Raises:
        CheckpointError: an unreadable checkpoint; ValueError: checkpoints of different presets or a
        segmenter the export does not support (SPVCNN); ExportError: a graph that fails validation.
    """
    import onnx
    import onnxruntime

    det, seg = detector, segmenter
    if det.preset != seg.preset:
        raise ValueError(f"detector is for preset {det.preset!r} but segmenter for {seg.preset!r}")
    profile = det.profile
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").unlink(missing_ok=True)
    detector_model, segmenter_model = det.build(), seg.build()
    mean_db, std_db = det.normalisation.get("mean", 0.0), det.normalisation.get("std", 1.0)
    export_detector(detector_model, profile, mean_db, std_db, out / "detector.onnx")
    layers = export_segmenter(segmenter_model, profile, out / "segmenter.onnx", column_gathers=True)
    n_range, n_angle, n_doppler = profile.shape
    detector_report = ComputeCounter(detector_model).report((1, n_doppler, n_range, n_angle))
    manifest = {
        "format": FORMAT, "version": VERSION, "opset": OPSET, "preset": profile.name,
        # a radar described by a file travels in the manifest, so an edge box needs no copy of the file
        "radar_file": describe_for_storage(profile),
        "cube_shape": list(profile.shape), "class_names": list(det.class_names),
        "normalisation": {"mean_db": float(mean_db), "std_db": float(std_db),
                          "applied": "detector: inside the graph; segmenter: feature 3 is (log_power - mean_db) / "
                                     "std_db, computed by the caller with the other features"},
        "detector": {
            "file": "detector.onnx", **validate(out / "detector.onnx"),
            "input_kind": "log power in dB, float32 (R, A, D) = cube_shape: 10 log10(|cube|^2 + 1) of the complex "
                          "RAD cube (radar.transforms.log_power)",
            "output_stride": int(getattr(detector_model, "output_stride", 4)),
            "history_frames": detector_history_frames(detector_model),
            **({"history_input": "history (H, R, A, D) float32: the H earlier frames' log power in dB as log_power, "
                                 "the latest first; history_present (H,) float32: 1 where that frame exists, 0 "
                                 "where not (its slice is ignored); all 0 is a single cube"}
               if detector_history_frames(detector_model) else {}),
            "macs": int(detector_report.macs), "params": count_params(detector_model),
            "checkpoint_sha256": checkpoint_digest(detector),
        },
        "segmenter": {
            "file": "segmenter.onnx", **validate(out / "segmenter.onnx"),
            "input_kind": "ROI voxels: features (N, 4) float32 = x / max_range, y / max_range, v / max_velocity, "
                          "normalised log power; the other inputs from kernel_maps_numpy.kernel_maps(coords (N, 3) "
                          "range, angle, Doppler bins)",
            "macs": "per frame, data-dependent: kernel_maps_numpy.segmenter_macs(maps, layers)",
            "layers": layers, "params": count_params(segmenter_model), "model": seg.model_name,
            "checkpoint_sha256": checkpoint_digest(segmenter),
        },
        "versions": {"torch": torch.__version__, "onnx": onnx.__version__, "onnxruntime": onnxruntime.__version__},
    }
    tmp = out / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2))
    os.replace(tmp, out / "manifest.json")
    return manifest
