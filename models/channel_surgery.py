"""Channel surgery: narrow a layer's weights, BatchNorm statistics and widths along kept channel indices.

The architecture-free half of network slimming (:mod:`models.slimming.prune` holds the selection and the
per-architecture tracers). The registered builders narrow a default build to a checkpoint's
``channels`` table through :func:`apply_channel_table`; this module imports no architecture, so a
builder can import it at module level without a cycle.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from models.sparse.conv import StridedConv3d, SubmanifoldConv3d, TransposedConv3d

NORM_TYPES = (nn.BatchNorm1d, nn.BatchNorm2d, nn.BatchNorm3d)  # the sparse BatchNorm subclasses BatchNorm1d
_CONVS = (nn.Conv1d, nn.Conv2d, nn.Conv3d)
_TRANSPOSED = (nn.ConvTranspose1d, nn.ConvTranspose2d, nn.ConvTranspose3d)


KERNEL_CONVS = (SubmanifoldConv3d, StridedConv3d, TransposedConv3d)  # weight (K, C_in, C_out)


def out_size(module: nn.Module) -> int:
    if isinstance(module, NORM_TYPES):
        return module.num_features
    if isinstance(module, nn.Linear):
        return module.out_features
    return module.out_channels


def weight_axes(module: nn.Module) -> tuple[int | None, int]:
    """(input axis, output axis) of a module's weight (input axis None for a BatchNorm)."""
    if isinstance(module, NORM_TYPES):
        return None, 0
    if isinstance(module, _TRANSPOSED):
        return 0, 1
    if isinstance(module, (*_CONVS, nn.Linear)):
        return 1, 0
    if isinstance(module, KERNEL_CONVS):
        return 1, 2
    raise ValueError(f"no channel surgery for {type(module).__name__}")


def in_size(module: nn.Module) -> int:
    return module.in_features if isinstance(module, nn.Linear) else module.in_channels


def is_depthwise(module: nn.Module) -> bool:
    return isinstance(module, _CONVS) and module.groups > 1 and module.groups == module.in_channels


@torch.no_grad()
def slice_module(module: nn.Module, in_index: Tensor | None, out_index: Tensor | None) -> None:
    """Narrow ``module`` in place to the given input/output channel indices (None: axis unchanged)."""
    if isinstance(module, NORM_TYPES):
        if out_index is None:
            return
        for name in ("weight", "bias"):
            if getattr(module, name) is not None:
                setattr(module, name, nn.Parameter(getattr(module, name)[out_index].clone()))
        for name in ("running_mean", "running_var"):
            if getattr(module, name) is not None:
                setattr(module, name, getattr(module, name)[out_index].clone())
        module.num_features = len(out_index)
        return
    in_axis, out_axis = weight_axes(module)
    weight = module.weight
    if is_depthwise(module):  # weight (C, 1, k, k): one axis, groups follow
        index = out_index if out_index is not None else in_index
        if index is None:
            return
        weight = weight.index_select(0, index)
        module.groups = module.in_channels = module.out_channels = len(index)
        in_index, out_index = None, index
    else:
        if getattr(module, "groups", 1) != 1 and (in_index is not None or out_index is not None):
            raise ValueError(f"cannot narrow a grouped (non-depthwise) {type(module).__name__}")
        if in_index is not None:
            weight = weight.index_select(in_axis, in_index)
        if out_index is not None:
            weight = weight.index_select(out_axis, out_index)
    module.weight = nn.Parameter(weight.clone())
    if getattr(module, "bias", None) is not None and out_index is not None:
        module.bias = nn.Parameter(module.bias[out_index].clone())
    if isinstance(module, nn.Linear):
        module.in_features, module.out_features = module.weight.shape[1], module.weight.shape[0]
    elif not is_depthwise(module):
        module.in_channels = weight.shape[in_axis] * getattr(module, "groups", 1)
        module.out_channels = weight.shape[out_axis]



def shape_entry(module: nn.Module) -> list[int] | None:
    if isinstance(module, NORM_TYPES):
        return [module.num_features]
    if isinstance(module, (*_CONVS, *_TRANSPOSED, nn.Linear, *KERNEL_CONVS)):
        return [in_size(module), out_size(module)]
    return None


def channel_table(model: nn.Module, reference: nn.Module) -> dict[str, list[int]]:
    """``{module path: [in, out]}`` (``[n]`` for a BatchNorm) of every layer of ``model`` whose width
    differs from the same layer of ``reference`` (the default build of the same config)."""
    ref = dict(reference.named_modules())
    table = {}
    for name, module in model.named_modules():
        entry = shape_entry(module)
        if entry is not None and name in ref and entry != shape_entry(ref[name]):
            table[name] = entry
    return table


def apply_channel_table(model: nn.Module, channels: dict[str, Sequence[int]]) -> nn.Module:
    """Narrow a freshly built default model to a ``channels`` table (the builders' ``channels=``).

    Layers keep their first channels (the weights are loaded afterwards). Raises ``ValueError`` naming
    a path that does not exist, a layer that cannot be narrowed, or a width that is not in
    ``[1, current width]``.
    """
    if not isinstance(channels, dict):
        raise ValueError(f"channels must be a dict of module path -> widths, got {type(channels).__name__}")
    modules = dict(model.named_modules())
    for path, dims in channels.items():
        module = modules.get(path)
        if module is None:
            raise ValueError(f"channels: {type(model).__name__} has no layer {path!r}")
        current = shape_entry(module)
        if current is None:
            raise ValueError(f"channels: layer {path!r} ({type(module).__name__}) has no channel widths")
        dims = [int(d) for d in dims]
        if len(dims) != len(current) or any(not 1 <= d <= c for d, c in zip(dims, current, strict=True)):
            raise ValueError(f"channels: layer {path!r} has widths {current}, cannot be narrowed to {dims}")
        if isinstance(module, NORM_TYPES):
            slice_module(module, None, torch.arange(dims[0]))
        elif is_depthwise(module):
            if dims[0] != dims[1]:
                raise ValueError(f"channels: depthwise layer {path!r} needs in == out, got {dims}")
            slice_module(module, None, torch.arange(dims[1]))
        else:
            slice_module(module, torch.arange(dims[0]) if dims[0] != current[0] else None,
                          torch.arange(dims[1]) if dims[1] != current[1] else None)
    return model
