"""ERASE-Net with its segmenter in int8 (``--precision int8``): the float model's fused segmenter quantised and
calibrated (:mod:`models.quantized.calibration`), the detector left float.

The detector is a dense 2-D network run by torch (oneDNN, traced and folded: ``FrozenDetector``); int8 there would
be torch's own quantisation, outside the compiled sparse engine, and in the ONNX export the int8 detector measured
slower than its float-compute graph on this kind of CPU (:mod:`models.export.quantize`: 4.8-4.9 against
3.7-3.8 ms), so it stays float (``benchmarks.int8_engine`` times it beside the segmenter).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

from models.quantized import calibration_cache
from models.quantized.calibration import calibrate, segmenter_inputs

if TYPE_CHECKING:
    from models.checkpoint import Checkpoint
    from models.erasenet.model import EraseNet
    from models.export.export_cache import Int8Calibration
    from models.quantized.segmenter import Int8MinkUNet

log = logging.getLogger(__name__)


def _fused_float(net: EraseNet) -> Any:
    """``net``'s fused float segmenter (ValueError when it has none)."""
    fused = net.segmenter_form
    if fused is None or getattr(fused, "precision", "float") != "float":
        raise ValueError("the torch-int8 runtime needs a fused MinkUNet segmenter (a plain MinkUNet, "
                         "fused_segmenter=True)")
    return fused


def int8_segmenter(net: EraseNet, calibration: Int8Calibration | None = None, *,
                   method: str = "max") -> Int8MinkUNet:
    """The int8 form of ``net``'s fused segmenter, calibrated on ``calibration``'s frames (default: simulated frames
    of the model's preset) through ``net``'s float pipeline.

    Raises:
        ValueError: ``net`` has no fused (plain MinkUNet) segmenter, or no calibration frame has ROI voxels.
    """
    from models.export.export_cache import Int8Calibration

    fused = _fused_float(net)
    calibration = calibration or Int8Calibration.simulated(net.profile)
    inputs = segmenter_inputs(net, calibration.cubes)
    log.info("int8 segmenter calibrated on %d frames (%s)", len(inputs), calibration.description.get("source"))
    return calibrate(fused, inputs, method)


def calibration_key(net: EraseNet, detector: Checkpoint, segmenter: Checkpoint,
                    calibration: Int8Calibration | None = None, *, method: str = "max") -> dict[str, Any]:
    """What :func:`int8_segmenter`'s ranges depend on (:func:`models.quantized.calibration_cache.calibration_key`):
    the checkpoints' sha256, the calibration frames (default simulated ones: their settings, not simulated here; a
    given calibration: its description and the frames' sha256) and ``net``'s seed settings."""
    from models.export import quantize
    from models.export.onnx_export import checkpoint_digest

    if calibration is None:  # what Int8Calibration.simulated(net.profile) would simulate
        frames = quantize.simulated_calibration_description(net.profile, quantize.CALIBRATION_FRAMES)
    else:
        frames = {"description": calibration.description,
                  "frames_sha256": quantize.calibration_digest(calibration.cubes)}
    pipeline = {"score_threshold": float(net.score_threshold), "max_objects": int(net.max_objects),
                "region_growing": repr(net.region_config), "doppler_refinement": repr(net.doppler_refinement),
                "normalisation": [net.mean_db, net.std_db]}
    return calibration_cache.calibration_key(
        detector_sha256=checkpoint_digest(detector), segmenter_sha256=checkpoint_digest(segmenter),
        frames=frames, pipeline=pipeline, method=method)


def to_int8(net: EraseNet, calibration: Int8Calibration | None = None, *, method: str = "max",
            checkpoints: tuple[Checkpoint, Checkpoint] | None = None) -> EraseNet:
    """``net`` with its segmenter run in int8 from now on (see :func:`int8_segmenter`); returns ``net``.

    ``checkpoints`` (the detector's and the segmenter's ``net`` was built from): the calibration is read from the
    calibration cache (:mod:`models.quantized.calibration_cache`) when it holds one for exactly these checkpoints,
    frames and settings, else calibrated and written there; a stale or corrupt entry is logged and replaced."""
    if checkpoints is None:
        int8 = int8_segmenter(net, calibration, method=method)
    else:
        fused = _fused_float(net)
        started = time.perf_counter()
        key = calibration_key(net, *checkpoints, calibration, method=method)
        path = calibration_cache.cache_path(key)
        int8, problem = calibration_cache.load(path, key, fused)
        if int8 is not None:
            log.info("int8 calibration read from %s (%.2f s)", path, time.perf_counter() - started)
        else:
            if problem != "none kept":
                log.warning("int8 calibration in %s not used (%s): calibrating again", path, problem)
            int8 = int8_segmenter(net, calibration, method=method)
            try:
                calibration_cache.save(path, key, int8)
            except OSError as exc:  # a read-only cache costs the next start a calibration, nothing else
                log.warning("int8 calibration not kept in %s: %s", path, exc)
    net.use_segmenter_form(int8)  # point_logits calls it as the fused float segmenter: (sparse) -> (logits, MAC tally)
    net.runtime = "torch-int8"
    return net
