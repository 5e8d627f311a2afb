"""ERASE-Net with its segmenter in int8 (``--precision int8``): the float model's fused segmenter quantised and
calibrated (:mod:`models.quantized.calibration`), the detector left float.

The detector is a dense 2-D network run by torch (oneDNN, traced and folded: ``FrozenDetector``); int8 there would
be torch's own quantisation, outside the compiled sparse engine, and in the ONNX export the int8 detector measured
slower than its float-compute graph on this kind of CPU (:mod:`models.export.quantize`: 4.8-4.9 against
3.7-3.8 ms), so it stays float (``benchmarks.int8_engine`` times it beside the segmenter).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

from models.quantized.calibration import calibrate, segmenter_inputs

if TYPE_CHECKING:
    from models.erasenet.model import EraseNet
    from models.export.export_cache import Int8Calibration
    from models.quantized.segmenter import Int8MinkUNet

log = logging.getLogger(__name__)

def int8_segmenter(net: EraseNet, calibration: Int8Calibration | None = None, *,
                   method: str = "max") -> Int8MinkUNet:
    """The int8 form of ``net``'s fused segmenter, calibrated on ``calibration``'s frames (default: simulated frames
    of the model's preset) through ``net``'s float pipeline.

    Raises:
        ValueError: ``net`` has no fused (plain MinkUNet) segmenter, or no calibration frame has ROI voxels.
    """
    from models.export.export_cache import Int8Calibration

    fused = getattr(net, "_fused", None)
    if fused is None or getattr(fused, "precision", "float") != "float":
        raise ValueError("--precision int8 needs the torch engine with a fused MinkUNet segmenter (a plain MinkUNet, "
                         "fused_segmenter=True)")
    calibration = calibration or Int8Calibration.simulated(net.profile)
    inputs = segmenter_inputs(net, calibration.cubes)
    log.info("int8 segmenter calibrated on %d frames (%s)", len(inputs), calibration.description.get("source"))
    return calibrate(fused, inputs, method)


def to_int8(net: EraseNet, calibration: Int8Calibration | None = None, *, method: str = "max") -> EraseNet:
    """``net`` with its segmenter run in int8 from now on (see :func:`int8_segmenter`); returns ``net``."""
    int8 = int8_segmenter(net, calibration, method=method)
    net._fused = int8  # point_logits calls it as the fused float segmenter: (sparse) -> (logits, MAC tally)
    net.precision = "int8"
    return net
