"""ERASE-Net on onnxruntime: the exported graphs behind :meth:`models.erasenet.model.EraseNet.segment`'s contract.

The same stages as the PyTorch engine (transform, detect, grow, segment, project) and the same result
and compute report (``compute.runtime == "onnx"``): the detector graph replaces the traced detector
(its outputs are decoded by the detector's own ``decode``), the segmenter graph replaces the sparse
MinkUNet (kernel maps from :mod:`models.export.kernel_maps_compiled`, equal to numpy's); region growing,
Doppler refinement, projection and objects are the shared code. Useful MACs are counted from the kernel maps
exactly as the PyTorch engine counts them; executed MACs are what the graph's matrix products run.

:mod:`models.export.export_cache` exports on demand into a cache keyed by the checkpoints' sha256
(``RADARSEG_ONNX_CACHE``, default ``~/.cache/radarseg/onnx``), so the .pt files are all it needs.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from models.checkpoint import Checkpoint
from models.erasenet.model import EraseNet
from models.export.kernel_maps_compiled import fastest_kernel_maps
from models.export.kernel_maps_numpy import segmenter_macs
from models.export.onnx_export import FORMAT, VERSION
from radar.profiles import RadarProfile
from radar.region_growing import Regions
from radar.roi import roi_points

log = logging.getLogger(__name__)

INT8_WEIGHTS = "int8-weights"
"""A graph's precision when it stores int8 weights and computes in float (``models.export.compact.int8_weights``)."""

def _session(path: Path, threads: int, *, fold_weights: bool = False):
    """``fold_weights``: a graph with int8 weights and float compute (:func:`models.export.compact.int8_weights`):
    its DequantizeLinear nodes folded into float weights when the session is built."""
    import onnxruntime as ort

    from models.export.compact import FOLD_WEIGHTS

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.log_severity_level = 3  # warnings about unused initialisers of the folded BatchNorms are noise
    if fold_weights:
        options.add_session_config_entry(*FOLD_WEIGHTS)
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


class OnnxDetector:
    """The detector graph called like the PyTorch detector: log power (R, A, D) (and, for a graph with
    ``history`` inputs, the earlier frames) -> dict of outputs, plus the detector's own ``decode``."""

    def __init__(self, session: Any, detector: nn.Module) -> None:
        self.session = session
        self.detector = detector
        self.output_names = [o.name for o in session.get_outputs()]
        inputs = {i.name: i.shape for i in session.get_inputs()}
        self.history_frames = int(inputs["history"][0]) if "history" in inputs else 0
        self._absent: dict[str, np.ndarray] | None = None  # the history feed of a single cube, made once

    def feed(self, log_power: np.ndarray, history: np.ndarray | None = None,
             history_present: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The graph's inputs: ``history`` (H, R, A, D) dB and ``history_present`` (H,) for a graph that reads
        earlier frames (without them, every earlier frame absent: the single cube)."""
        if not self.history_frames:
            if history is not None:
                raise ValueError("this detector graph reads one frame (history_frames 0): give no history")
            return {"log_power": log_power}
        if history is None:
            if self._absent is None:
                self._absent = {"history": np.zeros((self.history_frames, *log_power.shape), np.float32),
                                "history_present": np.zeros(self.history_frames, np.float32)}
            return {"log_power": log_power, **self._absent}
        return {"log_power": log_power, "history": history, "history_present": history_present}

    def __call__(self, log_power: np.ndarray, history: np.ndarray | None = None,
                 history_present: np.ndarray | None = None) -> dict[str, torch.Tensor]:
        outputs = self.session.run(None, self.feed(log_power, history, history_present))
        return {name: torch.from_numpy(value) for name, value in zip(self.output_names, outputs, strict=True)}

    def decode(self, outputs: dict[str, torch.Tensor], k: int = 100,
               score_threshold: float = 0.1) -> list[dict[str, torch.Tensor]]:
        return self.detector.decode(outputs, k=k, score_threshold=score_threshold)


class OnnxEraseNet(EraseNet):
    """:class:`EraseNet` whose detector and segmenter run as ONNX graphs in onnxruntime (CPU).

    The PyTorch modules are still built (parameter counts, the detector's analytic MACs and ``decode``) but
    never run.
    """

    runtime = "onnx"
    """"onnx" on float graphs, "onnx-int8" on quantised ones (the manifest's ``precision``)."""

    def __init__(self, detector: nn.Module, segmenter: nn.Module, profile: RadarProfile | str, *,
                 onnx_dir: str | Path, threads: int | None = None, **kwargs: Any) -> None:
        """``onnx_dir``: an export of these models (``radarseg export onnx``); ``threads``: onnxruntime's
        intra-op threads (default: torch's thread count, so one setting governs both engines)."""
        if torch.device(kwargs.get("device", "cpu")).type != "cpu":
            raise ValueError(f"the ONNX engine runs on the CPU, got device {kwargs['device']!r}")
        kwargs["frozen_detector"] = False  # the graph replaces the traced detector
        super().__init__(detector, segmenter, profile, **kwargs)
        self.onnx_dir = Path(onnx_dir)
        manifest_path = self.onnx_dir / "manifest.json"
        if not manifest_path.is_file():
            raise ValueError(f"{self.onnx_dir}: no ONNX export here (expected manifest.json; "
                             "run `radarseg export onnx`)")
        self.manifest = json.loads(manifest_path.read_text())
        if self.manifest.get("format") != FORMAT or self.manifest.get("version") != VERSION:
            raise ValueError(f"{manifest_path}: expected format {FORMAT!r} version {VERSION}, got "
                             f"{self.manifest.get('format')!r} version {self.manifest.get('version')!r}")
        if self.manifest["preset"] != self.profile.name or tuple(self.manifest["cube_shape"]) != self.profile.shape:
            raise ValueError(f"{self.onnx_dir}: exported for preset {self.manifest['preset']!r} "
                             f"{tuple(self.manifest['cube_shape'])}, not {self.profile.name!r} {self.profile.shape}")
        self.precision = self.manifest.get("precision", "float32")
        self.runtime = "onnx" if self.precision == "float32" else f"onnx-{self.precision}"
        threads = torch.get_num_threads() if threads is None else threads
        fold = self.manifest.get("detector", {}).get("precision") == INT8_WEIGHTS
        self._run_detector = OnnxDetector(_session(self.onnx_dir / "detector.onnx", threads, fold_weights=fold),
                                          self.detector)
        self._segmenter_session = _session(self.onnx_dir / "segmenter.onnx", threads)
        self._layers = self.manifest["segmenter"]["layers"]

    @property
    def history_frames(self) -> int:
        """Earlier frames the exported detector graph reads beside the cube (its ``history`` input; 0: one frame)."""
        return self._run_detector.history_frames

    @classmethod
    def from_checkpoints(cls, detector: Checkpoint, segmenter: Checkpoint, *,
                         onnx_dir: str | Path, int8: bool = False, **kwargs: Any) -> OnnxEraseNet:
        """Both stages from checkpoints, run from the export in ``onnx_dir`` (``models.export.export_cache`` makes
        and caches exports: :func:`models.export.export_cache.onnx_erasenet`). ``int8``: the export must hold the
        quantised graphs (ValueError otherwise, and for a float export asked as int8)."""
        net = super().from_checkpoints(detector, segmenter, onnx_dir=onnx_dir, **kwargs)
        if (net.precision == "int8") != int8:
            raise ValueError(f"{onnx_dir}: a {net.precision} export, but {'int8' if int8 else 'float32'} graphs "
                             "were asked for")
        return net

    normalises_detector_input = False  # the graph normalises

    def _detector_input(self, log_power: np.ndarray, *, in_place: bool = False) -> np.ndarray:
        return np.ascontiguousarray(log_power, dtype=np.float32)  # the graph normalises

    def _history_input(self, history: Sequence[np.ndarray | None]) -> dict[str, np.ndarray]:
        """The graph's ``history`` (H, R, A, D) dB, zero where absent, and ``history_present`` (H,) float32."""
        frames = self._earlier_frames(history)
        earlier = np.zeros((len(frames), *self.profile.shape), np.float32)
        for h, frame in enumerate(frames):
            if frame is not None:
                earlier[h] = frame
        return {"history": earlier, "history_present": np.array([frame is not None for frame in frames], np.float32)}

    def voxel_logits(self, coords: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
        """The segmenter graph on voxels (N, 3) bins with features (N, 4): logits (N, C), labels (N,) int64,
        useful and executed MACs."""
        maps = fastest_kernel_maps(coords)  # the compiled engine's where it runs, else numpy's
        logits, labels = self._segmenter_session.run(None, {"features": features, **maps})
        return (logits, labels, *segmenter_macs(maps, self._layers))

    def _segment_voxels(self, regions: Regions, log_power: np.ndarray) -> tuple[np.ndarray, int, int]:
        if len(regions) == 0:
            return np.zeros(0, np.uint8), 0, 0
        points = roi_points(regions.voxels, log_power, self.profile, mean_db=self.mean_db, std_db=self.std_db)
        _, labels, useful, executed = self.voxel_logits(points.coords, points.features)
        return labels.astype(np.uint8)[points.inverse], useful, executed
