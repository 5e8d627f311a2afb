"""Which code runs ERASE-Net: the PyTorch engine (``models.erasenet.model``) or the ONNX one (``models.export``).

Both give the same :class:`models.erasenet.model.EraseNet` interface and result; the compute report's
``engine`` says which ran.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # importing torch takes seconds: the CLI reads ENGINES before it knows what runs
    from models.checkpoint import Checkpoint
    from models.erasenet.model import EraseNet

ENGINES = ("torch", "onnx", "onnx-int8")
"""torch: the sparse engine of ``models.sparse`` and the traced detector; onnx: the exported graphs in
onnxruntime (exported on first use into the cache of ``models.export.export_cache``); onnx-int8: the same graphs
statically quantised (``models.export.quantize``), calibrated on simulated frames of the model's preset unless
``calibration=`` names a store."""

PRECISIONS = ("float", "int8")
"""What the torch engine's sparse segmenter computes in: float (the compiled float32 kernels), or int8 (the int8
kernels, ``models.quantized``: calibrated on ``calibration=``'s frames, default simulated frames of the preset; the
calibration is kept in ``models.quantized.calibration_cache`` and read back at the next load of the same pair)."""


def load_erasenet(detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint, *, engine: str = "torch",
                  precision: str = "float", **kwargs: Any) -> EraseNet:
    """``EraseNet.from_checkpoints`` on the chosen engine (keyword arguments as there) and ``precision``
    (:data:`PRECISIONS`; int8 on the torch engine only: the ONNX engine's int8 is ``onnx-int8``).

    Raises:
        ValueError: an engine not in :data:`ENGINES`, a precision not in :data:`PRECISIONS`, int8 on another engine.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "int8" and engine != "torch":
        from radar.errors import UserError

        raise UserError(f"precision int8 runs on the torch engine, not {engine!r} (the ONNX engine's int8 is "
                         f"onnx-int8)")
    from models.checkpoint import load_pair

    detector, segmenter = load_pair(detector, segmenter)  # the boundary: Checkpoints below
    if engine == "torch":
        from models.erasenet.model import EraseNet

        calibration = kwargs.pop("calibration", None)
        net = EraseNet.from_checkpoints(detector, segmenter, **kwargs)
        if precision == "int8":
            from models.quantized.erasenet import to_int8

            to_int8(net, calibration, checkpoints=(detector, segmenter))  # calibrated once, then read back
        return net
    from models.export.export_cache import onnx_erasenet

    return onnx_erasenet(detector, segmenter, int8=engine == "onnx-int8", **kwargs)
