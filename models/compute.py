"""Analytic parameter and MAC counts of our networks (docs/design.md section 10).

MACs are counted per layer from the layer's hyper-parameters and the shapes it sees, never by timing
or by tracing every op: convolutions (1-3 D, grouped and depthwise), transposed convolutions, linear
layers, ``nn.MultiheadAttention`` (projections and the two attention matmuls), and any module that
states its own cost. Elementwise ops, norms, activations, pooling and resampling are not counted,
which is also what ``torch.utils.flop_counter.FlopCounterMode`` does: ``macs`` equals its FLOPs / 2.
Biases are not counted.

Two conventions, both reported:

- ``macs`` (correct, = ``FlopCounterMode`` / 2): a transposed conv does ``C_in * (C_out / g) * k``
  MACs per *input* position (``k`` = kernel volume);
- ``macs_paper`` (the counter behind the paper's and MVRSS's figures, thop-style): a transposed conv
  is counted like a forward conv, ``C_out * (C_in / g) * k`` per *output* position. With stride ==
  kernel (the usual 2x2 stride-2 upsampling) this overcounts by ``k_h * k_w``. Every other layer is
  counted the same way in both.

Modules whose cost depends on the data (sparse convolutions) expose an int attribute ``last_macs``
after each forward; it is summed in (per call) and their children are not walked. A custom dense
module may instead define ``analytic_macs(inputs: tuple, output) -> int``, used in both conventions.

Use :class:`ComputeCounter` for dense models (cost fixed per input shape): it runs one forward on a
``meta``-device copy per new input shape (no real arithmetic, no side effects on the model such as
BatchNorm statistics) and caches the report, so per-request accounting is a dict lookup. For models
with data-dependent parts, wrap the real forward in :class:`MacRecorder`, whose hooks only multiply a
few integers per layer.
"""

from __future__ import annotations

import copy
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

_CONVS = (nn.Conv1d, nn.Conv2d, nn.Conv3d)
_TRANSPOSED_CONVS = (nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d)


@dataclass(frozen=True)
class ComputeReport:
    """Parameters and multiply-accumulates of one forward pass.

    ``macs``: correct count (``FlopCounterMode`` FLOPs / 2). ``macs_paper``: transposed convs counted
    per output position, as the paper's counter did. ``dynamic_macs``: the part of ``macs`` reported
    by data-dependent modules (``last_macs``). ``by_stage``: ``macs`` per top-level child module
    (``"(root)"`` for layers of the model itself). ``input_shapes``: the shapes counted for (batch
    included: MACs scale with the batch). ``executed_macs``: the MACs the kernels actually ran (a sparse
    conv on its GEMM path also multiplies the zeros of missing neighbours); None when equal to ``macs``.
    """

    params: int
    macs: int
    macs_paper: int
    dynamic_macs: int = 0
    by_stage: dict[str, int] = field(default_factory=dict)
    input_shapes: tuple[tuple[int, ...], ...] = ()
    executed_macs: int | None = None  # what the kernels ran (sparse GEMM paths multiply zeros too); None: = macs

    @property
    def gmacs(self) -> float:
        return self.macs / 1e9

    def __add__(self, other: ComputeReport) -> ComputeReport:
        """Sum of two stages' costs (params add too: two different networks)."""
        by_stage = dict(self.by_stage)
        for name, value in other.by_stage.items():
            by_stage[name] = by_stage.get(name, 0) + value
        return ComputeReport(
            params=self.params + other.params,
            macs=self.macs + other.macs,
            macs_paper=self.macs_paper + other.macs_paper,
            dynamic_macs=self.dynamic_macs + other.dynamic_macs,
            by_stage=by_stage,
            input_shapes=self.input_shapes + other.input_shapes,
            executed_macs=self.executed + other.executed,
        )

    @property
    def executed(self) -> int:
        """MACs the kernels ran (``executed_macs``, or ``macs`` where not recorded)."""
        return self.macs if self.executed_macs is None else self.executed_macs

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON, with the two MAC conventions labelled."""
        return {
            "params": self.params,
            "macs": self.macs,
            "macs_convention": "correct (FlopCounterMode FLOPs / 2)",
            "macs_paper": self.macs_paper,
            "macs_paper_convention": "transposed convs counted per output position (paper/thop)",
            "dynamic_macs": self.dynamic_macs,
            "executed_macs": self.executed,
            "by_stage": dict(self.by_stage),
            "input_shapes": [list(shape) for shape in self.input_shapes],
        }


def count_params(model: nn.Module, *, trainable_only: bool = False) -> int:
    """Number of parameters (shared ones once)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def _first_tensor(args: tuple) -> torch.Tensor:
    for arg in args:
        if isinstance(arg, torch.Tensor):
            return arg
    raise TypeError("layer called without a tensor argument")


def _conv_macs(module: nn.Module, inputs: tuple, output: torch.Tensor) -> tuple[int, int]:
    kernel = math.prod(module.kernel_size)
    if isinstance(module, _TRANSPOSED_CONVS):
        x = _first_tensor(inputs)
        correct = x.numel() * (module.out_channels // module.groups) * kernel
        paper = output.numel() * (module.in_channels // module.groups) * kernel
        return correct, paper
    macs = output.numel() * (module.in_channels // module.groups) * kernel
    return macs, macs


def _linear_macs(module: nn.Linear, inputs: tuple, output: torch.Tensor) -> tuple[int, int]:
    macs = output.numel() * module.in_features
    return macs, macs


def _attention_macs(module: nn.MultiheadAttention, inputs: tuple, output: Any) -> tuple[int, int]:
    query, key, value = inputs[:3]
    batch_first = module.batch_first
    if query.ndim == 2:  # unbatched (L, E)
        query, key, value = query[:, None], key[:, None], value[:, None]
        batch_first = False
    if batch_first:
        batch, tgt_len = query.shape[:2]
        src_len = key.shape[1]
    else:
        tgt_len, batch = query.shape[:2]
        src_len = key.shape[0]
    embed = module.embed_dim
    projections = batch * embed * (tgt_len * embed + src_len * module.kdim + src_len * module.vdim)
    attention = 2 * batch * tgt_len * src_len * embed  # Q K^T and A V over all heads
    out_proj = batch * tgt_len * embed * embed
    macs = projections + attention + out_proj
    return macs, macs


def layer_macs(module: nn.Module, inputs: tuple, output: Any) -> tuple[int, int] | None:
    """``(macs, macs_paper)`` of one call of a counted layer, ``None`` for layers not counted."""
    if isinstance(module, (*_CONVS, *_TRANSPOSED_CONVS)):
        return _conv_macs(module, inputs, output)
    if isinstance(module, nn.Linear):
        return _linear_macs(module, inputs, output)
    if isinstance(module, nn.MultiheadAttention):
        return _attention_macs(module, inputs, output)
    custom = getattr(module, "analytic_macs", None)
    if callable(custom):
        macs = int(custom(inputs, output))
        return macs, macs
    return None


def _stops_walk(module: nn.Module) -> bool:
    """Modules counted as a whole (their children are not walked)."""
    return (
        hasattr(module, "last_macs")
        or isinstance(module, nn.MultiheadAttention)
        or callable(getattr(module, "analytic_macs", None))
    )


def _counted_modules(model: nn.Module) -> list[tuple[str, nn.Module]]:
    found = []

    def walk(prefix: str, module: nn.Module) -> None:
        found.append((prefix, module))
        if _stops_walk(module):
            return
        for name, child in module.named_children():
            walk(f"{prefix}.{name}" if prefix else name, child)

    walk("", model)
    return found


class MacRecorder:
    """Context manager counting the MACs of every forward of ``model`` run inside it.

    ``with MacRecorder(model) as recorder: model(x)`` then ``recorder.report()``. Layers called several
    times are counted each time; modules with ``last_macs`` are read right after each of their calls.
    """

    def __init__(self, model: nn.Module, *, layers: list[tuple[str, nn.Module]] | None = None,
                 params: int | None = None) -> None:
        """Args:
            model: the model whose forwards are counted.
            layers: `counted_layers(model)` computed once by a caller that records every frame (walking the
                model and finding the counted layers costs more than the hooks themselves).
            params: `count_params(model)`, likewise.
        """
        self.model = model
        self._layers = layers
        self._params = params
        self.macs = 0
        self.macs_paper = 0
        self.dynamic_macs = 0
        self.executed_macs = 0
        self.by_stage: dict[str, int] = {}
        self.input_shapes: tuple[tuple[int, ...], ...] = ()
        self._handles: list[torch.utils.hooks.RemovableHandle] = []

    def _hook(self, name: str):
        stage = name.split(".", 1)[0] if name else "(root)"

        def hook(module: nn.Module, inputs: tuple, output: Any) -> None:
            if hasattr(module, "last_macs"):
                correct = paper = int(module.last_macs)
                self.dynamic_macs += correct
                self.executed_macs += int(getattr(module, "last_executed_macs", correct))
            else:
                counted = layer_macs(module, inputs, output)
                if counted is None:
                    return
                correct, paper = counted
                self.executed_macs += correct
            self.macs += correct
            self.macs_paper += paper
            self.by_stage[stage] = self.by_stage.get(stage, 0) + correct

        return hook

    def _record_inputs(self, module: nn.Module, args: tuple) -> None:
        self.input_shapes = tuple(tuple(a.shape) for a in args if isinstance(a, torch.Tensor))

    def __enter__(self) -> MacRecorder:
        self._handles.append(self.model.register_forward_pre_hook(self._record_inputs))
        for name, module in counted_layers(self.model) if self._layers is None else self._layers:
            self._handles.append(module.register_forward_hook(self._hook(name)))
        return self

    def __exit__(self, *exc_info: object) -> None:
        for handle in self._handles:
            handle.remove()
        self._handles.clear()

    def report(self) -> ComputeReport:
        return ComputeReport(
            params=count_params(self.model) if self._params is None else self._params,
            macs=self.macs,
            macs_paper=self.macs_paper,
            dynamic_macs=self.dynamic_macs,
            by_stage=dict(self.by_stage),
            input_shapes=self.input_shapes,
            executed_macs=self.executed_macs,
        )


def counted_layers(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """The (name, module) pairs whose forwards :class:`MacRecorder` counts."""
    return [(name, module) for name, module in _counted_modules(model)
            if hasattr(module, "last_macs") or layer_macs_applies(module)]


def layer_macs_applies(module: nn.Module) -> bool:
    """Whether :func:`layer_macs` counts this module type."""
    return isinstance(module, (*_CONVS, *_TRANSPOSED_CONVS, nn.Linear, nn.MultiheadAttention)) or callable(
        getattr(module, "analytic_macs", None)
    )


def _normalise_shapes(input_shapes: Sequence) -> tuple[tuple[int, ...], ...]:
    if not input_shapes:
        raise ValueError("give at least one input shape")
    shapes = []
    for shape in input_shapes:
        shape = tuple(int(s) for s in shape)
        if not shape or any(s < 1 for s in shape):
            raise ValueError(f"input shapes must be non-empty tuples of positive ints, got {shape}")
        shapes.append(shape)
    return tuple(shapes)


def _meta_copy(model: nn.Module) -> nn.Module:
    return copy.deepcopy(model).to("meta").eval()


def _count_on_meta(
    meta_model: nn.Module, shapes: tuple[tuple[int, ...], ...], params: int, dtype: torch.dtype
) -> ComputeReport:
    inputs = [torch.empty(shape, dtype=dtype, device="meta") for shape in shapes]
    with torch.no_grad(), MacRecorder(meta_model) as recorder:
        meta_model(*inputs)
    return ComputeReport(
        params=params,
        macs=recorder.macs,
        macs_paper=recorder.macs_paper,
        dynamic_macs=recorder.dynamic_macs,
        by_stage=dict(recorder.by_stage),
        input_shapes=shapes,
    )


def count_macs(model: nn.Module, *input_shapes: Sequence[int], dtype: torch.dtype = torch.float32) -> ComputeReport:
    """Report for one forward of ``model`` on inputs of ``input_shapes`` (batch included).

    Runs on a ``meta``-device deep copy in eval mode: no arithmetic, no change to ``model`` (eval also
    lets batch-1 shapes through BatchNorm on 1x1 maps). Only for models whose cost is fixed by the
    input shape (no ``last_macs`` modules, which need real data: use :class:`MacRecorder` on a real
    forward for those). Costs about as much as one real forward of a small model (the copy dominates);
    :class:`ComputeCounter` keeps the copy and caches per shape.
    """
    shapes = _normalise_shapes(input_shapes)
    return _count_on_meta(_meta_copy(model), shapes, count_params(model), dtype)


class ComputeCounter:
    """Per-input-shape cache of :func:`count_macs` for one dense model (cheap per request).

    ``counter.report((1, 64, 256, 256))`` costs one meta forward the first time (about 0.1 s for the
    detector, plus a one-off copy of the model to the meta device) and a dict lookup afterwards. Build
    a new counter when the architecture changes (e.g. after slimming).
    """

    def __init__(self, model: nn.Module, *, dtype: torch.dtype = torch.float32) -> None:
        self.model = model
        self.dtype = dtype
        self._meta_model: nn.Module | None = None
        self._cache: dict[tuple[tuple[int, ...], ...], ComputeReport] = {}
        # Hooks on the shared meta copy would mix two concurrent counts: one count at a time.
        self._lock = threading.Lock()

    def report(self, *input_shapes: Sequence[int]) -> ComputeReport:
        """Cached report for inputs of ``input_shapes`` (batch included); thread-safe."""
        shapes = _normalise_shapes(input_shapes)
        cached = self._cache.get(shapes)
        if cached is not None:
            return cached
        with self._lock:
            cached = self._cache.get(shapes)
            if cached is None:
                if self._meta_model is None:
                    self._meta_model = _meta_copy(self.model)
                cached = _count_on_meta(self._meta_model, shapes, count_params(self.model), self.dtype)
                self._cache[shapes] = cached
        return cached


def dynamic_macs(model: nn.Module) -> int:
    """Sum of ``last_macs`` over the modules exposing it (outermost only), after a real forward.

    Counts each module's most recent call only; use :class:`MacRecorder` when a module runs several
    times per forward.
    """
    return sum(int(module.last_macs) for _, module in _counted_modules(model) if hasattr(module, "last_macs"))
