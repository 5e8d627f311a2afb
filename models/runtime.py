"""What runs ERASE-Net, as one value: :class:`Runtime`, a backend and a precision, named as people type it.

- backend ``torch``: PyTorch, the sparse convolutions on :mod:`models.sparse`'s kernels and the traced detector;
  ``onnx``: the exported graphs in onnxruntime (exported on first use into the cache of
  :mod:`models.export.export_cache`).
- precision ``float``, or ``int8``: on torch, the segmenter in the compiled int8 sparse kernels
  (:mod:`models.quantized`, calibrated at load on ``calibration=``'s frames, default simulated frames of the preset,
  and kept in :mod:`models.quantized.calibration_cache`); on onnx, the graphs statically quantised
  (:mod:`models.export.quantize`).

The four names (:data:`RUNTIMES`) are what every command (``--runtime``), the service's models (``"runtime"``) and
the benchmarks take. "Engine" is not a runtime here: it names nothing but the sparse kernels' build
(:mod:`models.sparse.compiled`). Both give the same :class:`models.erasenet.model.EraseNet` interface and result;
the compute report's ``runtime`` says which ran.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from radar.errors import UserError

if TYPE_CHECKING:  # importing torch takes seconds: the CLI reads RUNTIMES before it knows what runs
    from models.checkpoint import Checkpoint
    from models.erasenet.model import EraseNet

BACKENDS = ("torch", "onnx")
PRECISIONS = ("float", "int8")
RUNTIMES = ("torch", "torch-int8", "onnx", "onnx-int8")
"""The runtimes by name: backend, then ``-int8`` for the int8 precision."""


@dataclasses.dataclass(frozen=True)
class Runtime:
    """A backend (:data:`BACKENDS`) and a precision (:data:`PRECISIONS`); :attr:`name` is how it is typed."""

    backend: str = "torch"
    precision: str = "float"

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise UserError(f"a runtime's backend is one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.precision not in PRECISIONS:
            raise UserError(f"a runtime's precision is one of {', '.join(PRECISIONS)}, got {self.precision!r}")

    @property
    def name(self) -> str:
        return self.backend if self.precision == "float" else f"{self.backend}-{self.precision}"

    def __str__(self) -> str:
        return self.name

    @classmethod
    def parse(cls, name: str | Runtime) -> Runtime:
        """The runtime named ``name`` (one of :data:`RUNTIMES`); a :class:`Runtime` is returned as it is."""
        if isinstance(name, Runtime):
            return name
        if name not in RUNTIMES:
            raise UserError(f"the runtime is one of {', '.join(RUNTIMES)}, got {name!r}")
        backend, _, precision = name.partition("-")
        return cls(backend, precision or "float")

    @classmethod
    def from_engine(cls, engine: str = "torch", precision: str = "float") -> Runtime:
        """The runtime the former pair of options named: ``engine`` torch, onnx or onnx-int8 and ``precision``
        float or int8 (``--engine onnx --precision int8`` is ``onnx-int8``)."""
        if engine not in ("torch", "onnx", "onnx-int8"):
            raise UserError(f"engine is one of torch, onnx, onnx-int8 (now --runtime {'|'.join(RUNTIMES)}), "
                            f"got {engine!r}")
        if engine == "onnx-int8":
            engine, precision = "onnx", "int8"
        return cls(engine, precision)


def load_erasenet(detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint,
                  runtime: Runtime | str = "torch", **kwargs: Any) -> EraseNet:
    """``EraseNet.from_checkpoints`` on ``runtime`` (a :class:`Runtime` or its name; keyword arguments as there,
    ``calibration=`` for the int8 runtimes, ``onnx_dir=`` for the onnx ones).

    Raises:
        UserError: a runtime not in :data:`RUNTIMES`.
    """
    runtime = Runtime.parse(runtime)
    from models.checkpoint import load_pair

    detector, segmenter = load_pair(detector, segmenter)  # the boundary: Checkpoints below
    if runtime.backend == "torch":
        from models.erasenet.model import EraseNet

        calibration = kwargs.pop("calibration", None)
        net = EraseNet.from_checkpoints(detector, segmenter, **kwargs)
        if runtime.precision == "int8":
            from models.quantized.erasenet import to_int8

            to_int8(net, calibration, checkpoints=(detector, segmenter))  # calibrated once, then read back
        return net
    from models.export.export_cache import onnx_erasenet

    return onnx_erasenet(detector, segmenter, int8=runtime.precision == "int8", **kwargs)
