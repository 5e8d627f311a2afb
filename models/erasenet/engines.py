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


def load_erasenet(detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint, *, engine: str = "torch",
                  **kwargs: Any) -> EraseNet:
    """``EraseNet.from_checkpoints`` on the chosen engine (keyword arguments as there).

    Raises:
        ValueError: an engine not in :data:`ENGINES`.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    from models.checkpoint import load_pair

    detector, segmenter = load_pair(detector, segmenter)  # the boundary: Checkpoints below
    if engine == "torch":
        from models.erasenet.model import EraseNet

        return EraseNet.from_checkpoints(detector, segmenter, **kwargs)
    from models.export.export_cache import onnx_erasenet

    return onnx_erasenet(detector, segmenter, int8=engine == "onnx-int8", **kwargs)
