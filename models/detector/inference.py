"""The centre detector in its fastest exact inference form: BatchNorms folded, channels_last, traced.

Measured at batch 1, one thread, side by side (benchmarks/detector.py, `inference_forms`; best of 9,
load 7 on 2 shared cores): eager 25.3 / 39.5 ms (small / carrada), channels_last 20.1 / 31.9, folded +
channels_last 22.1 / 26.9, folded + channels_last + traced 10.5 / 17.5 (`torch.jit.freeze` on top: the
same). Tracing removes the Python dispatch of ~300 small modules, which is most of the time at these
sizes; outputs equal the eager ones to float rounding (1e-7). TorchScript is deprecated in favour of
`torch.compile`, which needs a C++ toolchain at run time and compiles for tens of seconds per shape; the
deprecation warning is silenced around the one trace call.
"""

from __future__ import annotations

import copy
import warnings

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from models.layers import SeparableConv2d


def fold_batch_norms(module: nn.Module) -> int:
    """Fold every BatchNorm2d that directly follows a Conv2d (in an `nn.Sequential`, or a `SeparableConv2d`'s
    pointwise conv) into that conv, in place.

    The BatchNorm becomes `nn.Identity`; call on an eval-mode copy (the running statistics are baked in).

    Returns:
        How many BatchNorms were folded.
    """
    folded = 0
    for parent in module.modules():
        if isinstance(parent, SeparableConv2d) and isinstance(parent.norm, nn.BatchNorm2d):
            parent.pointwise = fuse_conv_bn_eval(parent.pointwise, parent.norm)
            parent.norm = nn.Identity()
            folded += 1
        if not isinstance(parent, nn.Sequential):
            continue
        names = list(parent._modules)
        for first, second in zip(names[:-1], names[1:], strict=True):
            conv, norm = parent._modules[first], parent._modules[second]
            if isinstance(conv, nn.Conv2d) and isinstance(norm, nn.BatchNorm2d):
                parent._modules[first] = fuse_conv_bn_eval(conv, norm)
                parent._modules[second] = nn.Identity()
                folded += 1
    return folded


class FrozenDetector(nn.Module):
    """A detector's forward with BatchNorms folded, in channels_last, traced for one input shape `(B, D, R, A)`.

    The graph holds a copy of the detector's weights at construction: later changes to `detector` do not
    reach it. `decode` is the detector's own.
    """

    def __init__(self, detector: nn.Module, input_shape: tuple[int, int, int, int],
                 device: torch.device | str = "cpu") -> None:
        """Trace and freeze.

        Args:
            detector: a detector whose `forward(log_power (B, D, R, A))` returns a dict of tensors and
                whose `decode(outputs, k=..., score_threshold=...)` reads them.
            input_shape: the one input shape the graph accepts.
            device: where the graph runs.
        """
        super().__init__()
        self.input_shape = tuple(int(v) for v in input_shape)
        self.detector = detector
        eager = copy.deepcopy(detector).to(device).eval()
        self.folded_batch_norms = fold_batch_norms(eager)
        eager = eager.to(memory_format=torch.channels_last)
        example = torch.zeros(self.input_shape, device=device).contiguous(memory_format=torch.channels_last)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            # The shape checks and padding become constants of the trace: the input shape is fixed above.
            warnings.simplefilter("ignore", torch.jit.TracerWarning)
            # No `check_trace`: it re-runs and re-traces the model to compare (2.7 of a model load's 4.3 s,
            # most of a service's start); tests/models compare the graph with the eager detector instead.
            self.graph = torch.jit.trace(eager, example, strict=False, check_trace=False)
        self._eager = eager  # kept for the history graph, traced at its first use
        self._history_graph: torch.jit.ScriptModule | None = None

    def forward(self, log_power: torch.Tensor, history: torch.Tensor | None = None,
                history_present: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The detector's outputs for a normalised input (B, D, R, A) of the traced shape (any layout); with
        ``history`` (B, H, D, R, A) and ``history_present`` (B, H), for a detector that reads earlier frames,
        through a second graph traced for them at the first call.

        Raises:
            ValueError: another input shape (the trace fixed its padding and shapes).
        """
        if tuple(log_power.shape) != self.input_shape:
            raise ValueError(f"frozen detector traced for input {self.input_shape}, got {tuple(log_power.shape)}")
        x = log_power.contiguous(memory_format=torch.channels_last)
        if history is None:
            return self.graph(x)
        present = (torch.ones(history.shape[:2], dtype=x.dtype, device=x.device) if history_present is None
                   else history_present.to(x.dtype))
        if self._history_graph is None:
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                self._history_graph = torch.jit.trace(self._eager, (x, history, present), strict=False,
                                                      check_trace=False)
        return self._history_graph(x, history, present)

    def decode(self, outputs: dict[str, torch.Tensor], k: int = 100,
               score_threshold: float = 0.1) -> list[dict[str, torch.Tensor]]:
        """The detector's own decoding."""
        return self.detector.decode(outputs, k=k, score_threshold=score_threshold)
