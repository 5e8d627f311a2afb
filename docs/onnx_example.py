"""ERASE-Net from its ONNX export with numpy, onnxruntime and the radar core alone: no torch, no models package.

    python docs/onnx_example.py ONNX_DIR CUBE.npy LABELS.npy [EARLIER.npy ...]

``ONNX_DIR`` is what ``radarseg export onnx`` wrote; ``CUBE.npy`` a complex RAD cube (R, A, D) of the export's
preset; ``EARLIER.npy`` the complex cubes of the frames before it in its sequence, the latest first, for a detector
that reads them (the manifest's ``detector.history_frames``; a frame not given counts as absent, as at the start of
a sequence). Writes the label cube (R, A, D) uint8 and prints the centres. The steps are those of
``models.erasenet.model.EraseNet.segment``: log power -> detector graph -> centres -> Doppler refinement -> region
growing -> ROI features and kernel maps -> segmenter graph -> labels. ``radar/`` (numpy, scipy, scikit-image)
does the radar steps; ``models/export/kernel_maps_numpy.py`` and ``centres_numpy.py`` (numpy only) are loaded by
file path, as a deployment that copies them would.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # for radar/ only: a deployment copies it (it imports nothing else of ours)

from radar import transforms  # noqa: E402
from radar.centres import Centres  # noqa: E402
from radar.doppler import DOPPLER_REFINEMENT, refine_doppler  # noqa: E402
from radar.profiles import resolve_profile  # noqa: E402
from radar.region_growing import RegionGrowingConfig, grow_regions  # noqa: E402
from radar.roi import roi_points  # noqa: E402


def load_by_path(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


kernel_maps_numpy = load_by_path(REPO / "models" / "export" / "kernel_maps_numpy.py")
centres_numpy = load_by_path(REPO / "models" / "export" / "centres_numpy.py")


def detector_feed(manifest: dict, log_power: np.ndarray, earlier: list[np.ndarray]) -> dict[str, np.ndarray]:
    """The detector graph's inputs: the frame's log power and, for a detector that reads ``history_frames`` earlier
    frames, theirs (H, R, A, D) dB with ``history_present`` (H,) 1 where given, 0 where absent (zeros then)."""
    n_history = manifest["detector"].get("history_frames", 0)
    if not n_history:
        return {"log_power": log_power}
    history = np.zeros((n_history, *log_power.shape), np.float32)
    present = np.zeros(n_history, np.float32)
    for h, frame in enumerate(earlier[:n_history]):
        if frame.shape != log_power.shape:
            raise ValueError(f"an earlier cube must have the cube's shape {log_power.shape}, got {frame.shape}")
        history[h], present[h] = frame, 1.0
    return {"log_power": log_power, "history": history, "history_present": present}


def segment(onnx_dir: Path, cube: np.ndarray, earlier: list[np.ndarray] = (), *, score_threshold: float = 0.3,
            max_objects: int = 32) -> np.ndarray:
    """Label cube (R, A, D) uint8 of one complex RAD cube (background outside the grown regions); ``earlier``: the
    complex cubes before it in its sequence, the latest first."""
    manifest = json.loads((onnx_dir / "manifest.json").read_text())
    # a built-in preset by name, or the radar the manifest itself describes (a profile file's contents)
    profile = resolve_profile(manifest["preset"], manifest.get("radar_file"), source=str(onnx_dir / "manifest.json"))
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    segmenter = ort.InferenceSession(str(onnx_dir / "segmenter.onnx"), options, providers=["CPUExecutionProvider"])
    if manifest["detector"].get("precision") == "int8-weights":  # an int8 export's detector: float compute on int8
        options.add_session_config_entry("session.disable_quant_qdq", "1")  # weights, folded once at load
    detector = ort.InferenceSession(str(onnx_dir / "detector.onnx"), options, providers=["CPUExecutionProvider"])

    log_power = transforms.log_power(cube)  # (R, A, D) dB; the detector graph normalises it itself
    earlier_log_power = [transforms.log_power(frame) for frame in earlier]
    heatmap, offset, doppler = detector.run(None, detector_feed(manifest, log_power, earlier_log_power))
    found = centres_numpy.decode_centres(heatmap, offset, doppler, k=max_objects, score_threshold=score_threshold,
                                         output_stride=manifest["detector"]["output_stride"])
    centres = refine_doppler(log_power, Centres.from_mapping(found), DOPPLER_REFINEMENT)
    regions = grow_regions(log_power, centres, profile, RegionGrowingConfig.for_profile(profile))
    labels = np.zeros(profile.shape, np.uint8)
    if len(regions) == 0:
        return labels
    norm = manifest["normalisation"]
    points = roi_points(regions.voxels, log_power, profile, mean_db=norm["mean_db"], std_db=norm["std_db"])
    feeds = {"features": points.features, **kernel_maps_numpy.kernel_maps(points.coords)}
    _, voxel_labels = segmenter.run(None, feeds)
    labels[tuple(regions.voxels.T)] = voxel_labels[points.inverse]
    for score, r, a, d in zip(centres.score, centres.range_bin, centres.angle_bin, centres.doppler_bin, strict=True):
        print(f"centre score {score:.2f} at range bin {r:.1f}, angle bin {a:.1f}, Doppler bin {d:.1f}")
    return labels


if __name__ == "__main__":
    onnx_dir, cube_path, out = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    earlier_cubes = [np.load(path, allow_pickle=False) for path in sys.argv[4:]]
    np.save(out, segment(onnx_dir, np.load(cube_path, allow_pickle=False), earlier_cubes))
    ours = sorted({m.split(".")[0] for m in sys.modules} & {"torch", "models", "pipelines", "service"})
    print(f"labels written to {out}; modules of torch or this package imported: {ours or 'none'}")
