"""Network slimming (docs/design.md section 11): BatchNorm-scale sparsity, global channel selection, real surgery.

Three steps, as in Liu et al. (2017) and the paper:

1. **Sparsity training**: :func:`slimming_penalty` is the L1 norm of every BatchNorm scale (dense
   ``BatchNorm1d/2d/3d`` and the sparse :class:`models.sparse.BatchNorm`); the trainers add
   ``lambda * penalty`` to the loss (``--slim-lambda``, 1e-4 by default when slimming).
2. **Selection**: :func:`trace_channels` describes a model as *channel groups*: sets of channels that
   must be kept or removed together because they are one index space of the network (a conv's
   output, its BatchNorm, the depthwise conv and squeeze-excite that act on it, every consumer's input
   slice, and everything a residual sum or a BiFPN fusion adds into it). A group channel's importance
   is the largest ``|gamma|`` over the group's BatchNorms (a tied channel is only removed when every
   BatchNorm carrying it says so). One global threshold over all groups removes the ``ratio`` least
   important channels (:func:`select_channels`), or the ratio is searched for a params/MACs budget
   (:func:`prune_checkpoint` with ``params=`` or ``macs=``). A group never loses its last
   ``min_channels`` channels; groups without a BatchNorm (detector heads, SE bottlenecks, transposed convs
   of the baselines, ASPP image pooling) are kept whole.
3. **Surgery**: :func:`prune_model` slices every weight, bias and running statistic of the members
   along the kept indices (concatenated inputs, as in U-Net skips and the multi-view decoders, take
   each part's kept indices at its offset), giving a genuinely narrower network, not a mask.

**Architecture travels with the checkpoint.** A pruned model is described by its builder's config plus
a ``channels`` table ``{module path: [in, out]}`` (``[n]`` for a BatchNorm) holding the layers whose
shape differs from the default build (:func:`channel_table`). Every registered builder takes
``channels=`` and, when given, narrows the default model with :func:`apply_channel_table` (which also
keeps depthwise convs depthwise); nothing else in the forward code depends on widths, and residual
shortcut types are decided by the default build, so a block whose pruned input and output widths
happen to match keeps its projection. :func:`prune_checkpoint` checks the round trip (rebuild from the
config alone, strict ``load_state_dict``) before returning, so a pruned checkpoint loads wherever
checkpoints load (:class:`models.erasenet.EraseNet`, the service) and reports its smaller MACs there.

**Torch-Pruning or our own surgery.** Torch-Pruning 1.6 (``BNScalePruner`` with ``regularize()``)
prunes the detector (depthwise, SE and residual ties found by tracing; the BiFPN fusion weights must be
listed in ``ignored_layers``/unwrapped parameters) and, through a custom pruner slicing ``[K, C_in,
C_out]``, our sparse convs (docs/design.md section 11). We wrote the surgery ourselves because:

- Torch-Pruning mutates module objects in place and keeps no description of the result; a checkpoint
  rebuilt by ``create_model(name, **config)`` still needs the ``channels`` table and the code that
  narrows a default build to it, which is most of what the surgery is;
- its graph comes from tracing autograd with example inputs. Our sparse layers run a custom
  ``autograd.Function`` over kernel maps built from coordinates, features travel inside
  ``SparseTensor``/``PointTensor`` containers, and SPVCNN sums point-MLP outputs into devoxelised
  features: each needs custom pruners and example inputs of the right kind, and a tracing miss is a
  silent wrong tie. Here the ties are written once per architecture family from the module structure
  (about 40 lines each), and the exactness tests (zeroed channels removed, outputs unchanged) check them;
- measured here with torch-pruning 1.6.1 (``BNScalePruner``, global ratio 0.4, head outputs ignored): on
  ``centre_detector_tiny`` it pruned 67,335 -> 32,668 params with correct outputs but left the BiFPN at
  its full width (it does not prune through the fusion weights); on ``minkunet_tiny`` its tracer failed
  at once (``'SparseTensor' object has no attribute 'grad_fn'``) before any custom pruner could help;
- no new dependency in the service image, and the same code serves the trainers' L1 penalty.

The cost is that a new architecture needs its tracer (:data:`TRACERS`, named by the class's
``channel_tracer``: :mod:`models.capabilities`); :func:`trace_channels` refuses a model it does not know
instead of guessing.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from models.capabilities import dense_input_shapes
from models.channel_surgery import NORM_TYPES, channel_table, out_size, slice_module
from models.checkpoint import Checkpoint
from models.compute import count_macs, count_params
from models.detector.bifpn import BiFPNNeck
from models.detector.efficientnet import EfficientNetBackbone
from models.layers import SeparableConv2d
from models.registry import create_model
from models.segmenter.spvcnn import FUSE_AFTER_DECODER_STAGE
from radar.errors import UserError

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- sparsity training
def batch_norms(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """Every affine BatchNorm of ``model`` (dense and sparse), with its module path."""
    return [(name, m) for name, m in model.named_modules() if isinstance(m, NORM_TYPES) and m.affine]


def slimming_penalty(model: nn.Module) -> Tensor:
    """L1 norm of all BatchNorm scales: ``sum |gamma|`` (a scalar on the scales' device, differentiable)."""
    scales = [m.weight.abs().sum() for _, m in batch_norms(model)]
    if not scales:
        raise ValueError(f"{type(model).__name__} has no BatchNorm: nothing to slim")
    return torch.stack(scales).sum()


# --------------------------------------------------------------------------- channel groups
@dataclass(eq=False)
class ChannelGroup:
    """Channels that are removed together.

    ``members``: ``(module, role, offset)`` with role ``out`` (the module's output axis; BatchNorms too),
    ``in`` (its input axis, the group starting at ``offset`` of a concatenated input) or ``dw`` (a
    depthwise conv, whose one weight axis is the group). ``norms``: the BatchNorms whose scales rank
    the channels; a group without any is kept whole.
    """

    name: str
    size: int
    norms: list[_NormSlice] = field(default_factory=list)
    members: list[tuple[nn.Module, str, int]] = field(default_factory=list)

    @property
    def prunable(self) -> bool:
        return bool(self.norms)

    def importance(self) -> Tensor:
        """(size,) largest ``|gamma|`` over the group's BatchNorms (``inf`` when it has none)."""
        if not self.norms:
            return torch.full((self.size,), float("inf"))
        return torch.stack([bn.weight.detach().abs().float().cpu() for bn in self.norms]).amax(dim=0)


Space = list[ChannelGroup]  # the channels of one tensor: groups concatenated in order


class _Tracer:
    """Collects groups while a tracer walks a model's structure."""

    def __init__(self) -> None:
        self.groups: list[ChannelGroup] = []

    def produced(self, name: str, module: nn.Module, norm: nn.Module | None = None) -> Space:
        """A new group: the output of ``module`` (and of the BatchNorm ``norm`` that follows it)."""
        group = ChannelGroup(name, out_size(module))
        self.groups.append(group)
        space = [group]
        self.produce(space, module, norm)
        return space

    def fixed(self, name: str, module: nn.Module) -> Space:
        """The output of a layer without BatchNorm: a group that is never pruned."""
        return self.produced(name, module)

    @staticmethod
    def produce(space: Space, module: nn.Module, norm: nn.Module | None = None) -> None:
        """``module`` (and ``norm``) write into the existing ``space`` (a residual or fused sum)."""
        offset = 0
        for group in space:
            group.members.append((module, "out", offset))
            if norm is not None:
                group.members.append((norm, "out", offset))
                group.norms.append(_NormSlice(norm, offset, group.size))
            offset += group.size

    @staticmethod
    def consume(space: Space, module: nn.Module) -> None:
        offset = 0
        for group in space:
            group.members.append((module, "in", offset))
            offset += group.size

    @staticmethod
    def depthwise(space: Space, module: nn.Module, norm: nn.Module | None = None) -> None:
        if len(space) != 1:
            raise ValueError("a depthwise conv over a concatenation is not supported")
        group = space[0]
        group.members.append((module, "dw", 0))
        if norm is not None:
            group.members.append((norm, "out", 0))
            group.norms.append(_NormSlice(norm, 0, group.size))


class _NormSlice:
    """The part ``[offset, offset + size)`` of a BatchNorm that belongs to one group."""

    def __init__(self, norm: nn.Module, offset: int, size: int) -> None:
        self.norm, self.offset, self.size = norm, offset, size

    @property
    def weight(self) -> Tensor:
        return self.norm.weight[self.offset:self.offset + self.size]


# ----- tracers, one per architecture family
def _trace_detector(model: nn.Module, t: _Tracer) -> None:

    backbone, neck = model.backbone, model.neck
    if not isinstance(backbone, EfficientNetBackbone) or not isinstance(neck, BiFPNNeck):
        raise ValueError("slimming supports the detector with its MBConv backbone and BiFPN neck only")
    cur = t.produced("stem", backbone.stem[0], backbone.stem[1])
    taps = []
    for s, stage in enumerate(backbone.stages):
        for b, block in enumerate(stage):
            name = f"stage{s}.block{b}"
            if isinstance(block.expand, nn.Identity):
                mid = cur  # the depthwise conv runs on the block input itself
            else:
                t.consume(cur, block.expand[0])
                mid = t.produced(f"{name}.mid", block.expand[0], block.expand[1])
            t.depthwise(mid, block.depthwise[0], block.depthwise[1])
            if not isinstance(block.se, nn.Identity):  # the gate is per channel of mid
                t.consume(mid, block.se.reduce)
                t.produce(mid, block.se.expand)
            t.consume(mid, block.project[0])
            if block.residual:  # out = project(x) + x: one index space with the input
                t.produce(cur, block.project[0], block.project[1])
            else:
                cur = t.produced(f"{name}.out", block.project[0], block.project[1])
        if s in backbone.feature_stages:
            taps.append(cur)
    # BiFPN: every node's output is summed (fast fusion) into the others, so the neck is one space.
    bifpn = neck.bifpn
    t.consume(taps[0], neck.c2_project[0])
    space = t.produced("neck", neck.c2_project[0], neck.c2_project[1])
    for tap, lateral in zip(taps[1:], bifpn.lateral, strict=True):
        t.consume(tap, lateral[0])
        t.produce(space, lateral[0], lateral[1])
    t.consume(taps[-1], bifpn.p6_project[0])
    t.produce(space, bifpn.p6_project[0], bifpn.p6_project[1])
    nodes = [node for layer in bifpn.layers for node in (*layer.top_down, *layer.bottom_up)] + [neck.stride4]
    for node in nodes:
        t.depthwise(space, node.conv.depthwise)
        t.consume(space, node.conv.pointwise)
        t.produce(space, node.conv.pointwise, node.conv.norm)
    for branch in (model.head.heatmap, model.head.offset, model.head.doppler):
        hidden = branch[0]
        if isinstance(hidden, SeparableConv2d):
            t.depthwise(space, hidden.depthwise)
            t.consume(space, hidden.pointwise)
        else:
            t.consume(space, hidden[0])


def _residual_stack(t: _Tracer, stack: nn.Sequential, cur: Space, name: str) -> Space:
    for b, block in enumerate(stack):
        t.consume(cur, block.main[0])
        mid = t.produced(f"{name}.block{b}.mid", block.main[0], block.main[1])
        t.consume(mid, block.main[3])
        if isinstance(block.shortcut, nn.Identity):
            out = cur
        else:
            t.consume(cur, block.shortcut[0].linear)
            out = t.produced(f"{name}.block{b}.out", block.shortcut[0].linear, block.shortcut[1])
        t.produce(out, block.main[3], block.main[4])
        cur = out
    return cur


def _trace_segmenter(model: nn.Module, t: _Tracer, *, points: bool = False) -> None:
    """MinkUNet; with ``points`` SPVCNN (its point MLPs add into the bottleneck and decoder spaces)."""
    first = t.produced("stem.0", model.stem[0][0], model.stem[0][1])
    t.consume(first, model.stem[1][0])
    cur = t.produced("stem.1", model.stem[1][0], model.stem[1][1])
    skips = [cur]
    for i, stage in enumerate(model.encoder):
        t.consume(cur, stage[0][0])
        down = t.produced(f"encoder{i}.down", stage[0][0], stage[0][1])
        cur = _residual_stack(t, stage[1], down, f"encoder{i}")
        skips.append(cur)
    if points:  # point MLP 0: stem features (devoxelised) -> added to the bottleneck features
        mlp = model.point_mlps[0]
        t.consume(skips[0], mlp[0].linear)
        t.produce(cur, mlp[0].linear, mlp[1])
    point_space = cur
    for i, (stage, skip) in enumerate(zip(model.decoder, reversed(skips[:-1]), strict=True)):
        t.consume(cur, stage.up[0])
        up = t.produced(f"decoder{i}.up", stage.up[0], stage.up[1])
        cur = _residual_stack(t, stage.fuse, up + skip, f"decoder{i}")
        mlp_index = FUSE_AFTER_DECODER_STAGE.get(i) if points else None
        if mlp_index is not None:
            mlp = model.point_mlps[mlp_index]
            t.consume(point_space, mlp[0].linear)
            t.produce(cur, mlp[0].linear, mlp[1])
            point_space = cur
    t.consume(cur, model.classifier.linear)


def _conv_unit(t: _Tracer, cur: Space, unit: nn.Sequential, name: str) -> Space:
    """conv -> BatchNorm -> activation, as a Sequential."""
    t.consume(cur, unit[0])
    return t.produced(name, unit[0], unit[1])


def _trace_multiview(model: nn.Module, t: _Tracer) -> None:
    summary, latent = {}, {}
    for view, encoder in model.encoders.items():
        frames = encoder.frames
        if model.temporal:  # Conv3d, BN3d, act, Conv3d, BN3d, act
            first = t.produced(f"{view}.frames.0", frames[0], frames[1])
            t.consume(first, frames[3])
            cur = t.produced(f"{view}.frames.1", frames[3], frames[4])
        else:
            first = t.produced(f"{view}.frames.0", frames[0][0], frames[0][1])
            cur = _conv_unit(t, first, frames[1], f"{view}.frames.1")
        cur = _conv_unit(t, cur, encoder.conv[0], f"{view}.conv.0")
        features = _conv_unit(t, cur, encoder.conv[1], f"{view}.conv.1")
        latent[view] = _conv_unit(t, features, encoder.latent, f"{view}.latent")
        aspp = model.aspp[view]
        parts: Space = []
        for i, branch in enumerate(aspp.branches):
            parts += _conv_unit(t, features, branch, f"{view}.aspp.{i}")
        t.consume(features, aspp.pool_conv)
        parts += t.fixed(f"{view}.aspp.pool", aspp.pool_conv)
        summary[view] = _conv_unit(t, parts, model.aspp_fuse[view], f"{view}.aspp_fuse")
    for view, decoder in model.decoders.items():
        fused = _conv_unit(t, latent["rd"] + latent["ra"] + latent["ad"], model.latent_fuse[view],
                           f"{view}.latent_fuse")
        t.consume(summary[view] + fused + summary["ad"], decoder.up1)
        cur = t.fixed(f"{view}.up1", decoder.up1)
        cur = _conv_unit(t, cur, decoder.conv1[0], f"{view}.conv1.0")
        cur = _conv_unit(t, cur, decoder.conv1[1], f"{view}.conv1.1")
        t.consume(cur, decoder.up2)
        cur = t.fixed(f"{view}.up2", decoder.up2)
        cur = _conv_unit(t, cur, decoder.conv2[0], f"{view}.conv2.0")
        cur = _conv_unit(t, cur, decoder.conv2[1], f"{view}.conv2.1")
        t.consume(cur, decoder.classifier)


def _trace_unet(model: nn.Module, t: _Tracer) -> None:
    def double(cur: Space, block: nn.Sequential, name: str) -> Space:
        return _conv_unit(t, _conv_unit(t, cur, block[0], f"{name}.0"), block[1], f"{name}.1")

    skips = [double([], model.stem, "stem")]
    for i, stage in enumerate(model.down):
        skips.append(double(skips[-1], stage, f"down{i}"))
    cur = skips.pop()
    for i, stage in enumerate(model.up):
        t.consume(cur, stage.up)
        up = t.fixed(f"up{i}.transposed", stage.up)
        cur = double(skips.pop() + up, stage.conv, f"up{i}")  # forward: cat([skip, up])
    t.consume(cur, model.classifier)


def _trace_points_segmenter(model: nn.Module, t: _Tracer) -> None:
    _trace_segmenter(model, t, points=True)


# A model names its tracer by its class attribute ``channel_tracer`` (models.capabilities).
TRACERS: dict[str, Callable[[nn.Module, _Tracer], None]] = {
    "detector": _trace_detector,  # CentreDetector
    "sparse_unet": _trace_segmenter,  # MinkUNet
    "sparse_unet_points": _trace_points_segmenter,  # SPVCNN
    "multiview": _trace_multiview,  # TMVA-Net, SMVA-Net
    "unet": _trace_unet,
}
SUPPORTED = "CentreDetector, MinkUNet, SPVCNN, MultiViewNet (TMVA-Net, SMVA-Net), UNet"


def trace_channels(model: nn.Module) -> list[ChannelGroup]:
    """The channel groups of a supported model (see the module docstring); raises ``ValueError`` otherwise."""
    tracer = TRACERS.get(getattr(model, "channel_tracer", None))
    if tracer is None:
        raise ValueError(f"slimming does not know {type(model).__name__}: supported are {SUPPORTED}")
    t = _Tracer()
    tracer(model, t)
    return t.groups


# --------------------------------------------------------------------------- selection
@dataclass(frozen=True)
class Selection:
    """Kept channel indices per group and the global threshold that chose them."""

    keep: dict[int, Tensor]  # index into the group list -> sorted kept indices
    threshold: float  # importance of the least important kept channel among the candidates
    removed: int  # channels removed (over prunable groups)
    candidates: int  # channels in prunable groups


def select_channels(groups: Sequence[ChannelGroup], ratio: float, *, min_channels: int = 1) -> Selection:
    """Remove the ``ratio`` fraction of prunable channels with the smallest importance, globally.

    Ties are broken by position. A group keeps at least ``min(min_channels, size)`` channels (its most
    important ones), so no layer is ever emptied; the removed count can then fall short of the ratio.
    """
    if not 0 <= ratio < 1:
        raise ValueError(f"ratio must be in [0, 1), got {ratio}")
    if min_channels < 1:
        raise ValueError(f"min_channels must be >= 1, got {min_channels}")
    prunable = [i for i, g in enumerate(groups) if g.prunable]
    scores = [groups[i].importance() for i in prunable]
    keep = {i: torch.arange(g.size) for i, g in enumerate(groups)}
    total = sum(len(s) for s in scores)
    n_remove = int(round(ratio * total))
    if n_remove == 0 or not scores:
        return Selection(keep, 0.0, 0, total)
    flat = torch.cat(scores)
    order = torch.argsort(flat, stable=True)
    removed_mask = torch.zeros(total, dtype=torch.bool)
    removed_mask[order[:n_remove]] = True
    threshold = float(flat[order[n_remove]]) if n_remove < total else float("inf")
    start, removed = 0, 0
    for i, score in zip(prunable, scores, strict=True):
        drop = removed_mask[start:start + len(score)].clone()
        start += len(score)
        floor = min(min_channels, len(score))
        if int((~drop).sum()) < floor:  # never empty a layer: keep its best channels
            drop[:] = True
            drop[torch.argsort(score, descending=True, stable=True)[:floor]] = False
        keep[i] = torch.nonzero(~drop).flatten()
        removed += int(drop.sum())
    return Selection(keep, threshold, removed, total)


# --------------------------------------------------------------------------- surgery
def prune_model(model: nn.Module, groups: Sequence[ChannelGroup], keep: dict[int, Tensor]) -> nn.Module:
    """Remove channels in place: every member of every group is sliced to the kept indices.

    An axis holding several groups (a concatenation) takes each group's kept indices at its offset.
    Returns ``model``.
    """
    segments: dict[nn.Module, dict[str, list[tuple[int, Tensor]]]] = {}
    for i, group in enumerate(groups):
        for module, role, offset in group.members:
            axis = "in" if role == "in" else "out"
            segments.setdefault(module, {"in": [], "out": []})[axis].append((offset, keep[i] + offset))
    for module, axes in segments.items():
        index = {}
        for axis, parts in axes.items():
            if not parts:
                index[axis] = None
                continue
            parts = sorted({offset: idx for offset, idx in parts}.items())  # a module may produce a space twice
            index[axis] = torch.cat([idx for _, idx in parts])
        slice_module(module, index["in"], index["out"])
    return model


# --------------------------------------------------------------------------- the channels table
# --------------------------------------------------------------------------- checkpoints and budgets
@dataclass(frozen=True)
class PruneReport:
    """What a pruning did: ratio, threshold, params (and dense MACs) before/after, group widths."""

    ratio: float
    threshold: float
    removed_channels: int
    candidate_channels: int
    params_before: int
    params_after: int
    macs_before: int | None = None
    macs_after: int | None = None
    widths: dict[str, tuple[int, int]] = field(default_factory=dict)  # prunable group -> (before, after)

    def to_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}


def _macs(model: nn.Module, shapes: tuple[tuple[int, ...], ...] | None) -> int | None:

    return None if shapes is None else count_macs(model, *shapes).macs


def prune(model: nn.Module, ratio: float, *, min_channels: int = 1) -> tuple[nn.Module, Selection,
                                                                              list[ChannelGroup]]:
    """A pruned deep copy of ``model`` (the original is untouched), the selection and the groups."""
    pruned = copy.deepcopy(model)
    groups = trace_channels(pruned)
    selection = select_channels(groups, ratio, min_channels=min_channels)
    prune_model(pruned, groups, selection.keep)
    return pruned, selection, groups


def prune_checkpoint(checkpoint: Any, *, ratio: float | None = None, params: int | None = None,
                     macs: int | None = None, min_channels: int = 1) -> tuple[Any, PruneReport]:
    """Prune a :class:`models.checkpoint.Checkpoint` by global ``ratio`` or to a ``params``/``macs`` budget.

    Returns the pruned checkpoint (same model name, config plus the ``channels`` table, pruned weights;
    ``extra["slimming"]`` holds the report) and the :class:`PruneReport`. The checkpoint is rebuilt
    from its config alone and loaded strictly before it is returned.
    """

    if sum(v is not None for v in (ratio, params, macs)) != 1:
        raise UserError("give exactly one of ratio, params or macs")
    model = checkpoint.build()
    shapes = dense_input_shapes(model, checkpoint.preset)
    if ratio is None:
        ratio = _budget_ratio(model, params=params, macs=macs, shapes=shapes, min_channels=min_channels)
    pruned, selection, groups = prune(model, ratio, min_channels=min_channels)
    base_config = {k: v for k, v in checkpoint.config.items() if k != "channels"}
    config = {**base_config, "channels": channel_table(pruned, create_model(checkpoint.model_name, **base_config))}
    state = {k: v.detach().clone() for k, v in pruned.state_dict().items()}
    rebuilt = create_model(checkpoint.model_name, **config)
    rebuilt.load_state_dict(state)  # strict: the table describes exactly the pruned shapes
    report = PruneReport(
        ratio=float(ratio), threshold=selection.threshold, removed_channels=selection.removed,
        candidate_channels=selection.candidates, params_before=count_params(model), params_after=count_params(rebuilt),
        macs_before=_macs(model, shapes), macs_after=_macs(rebuilt, shapes),
        widths={g.name: (g.size, int(len(selection.keep[i]))) for i, g in enumerate(groups) if g.prunable})
    extra = {**checkpoint.extra, "slimming": {k: v for k, v in report.to_dict().items() if k != "widths"}}
    for key in ("optimizer", "scheduler"):  # optimiser state of the wide model does not fit the narrow one
        extra.pop(key, None)
    pruned_ckpt = Checkpoint(model_name=checkpoint.model_name, config=config, state_dict=state,
                             preset=checkpoint.preset, class_names=checkpoint.class_names,
                             normalisation=dict(checkpoint.normalisation), extra=extra)
    return pruned_ckpt, report


def _budget_ratio(model: nn.Module, *, params: int | None, macs: int | None, shapes, min_channels: int,
                  iterations: int = 14) -> float:
    """Smallest global ratio whose pruned model fits the budget (bisection; cost falls with the ratio)."""

    if macs is not None and shapes is None:
        raise UserError(f"{type(model).__name__}: MACs depend on the input voxels; give a params budget")
    budget = params if params is not None else macs
    if budget is None or budget < 1:
        raise UserError(f"budget must be a positive count, got {budget}")

    def cost(ratio: float) -> int:
        pruned = prune(model, ratio, min_channels=min_channels)[0]
        return count_params(pruned) if params is not None else _macs(pruned, shapes)

    if cost(0.0) <= budget:
        return 0.0
    low, high = 0.0, 0.99
    if cost(high) > budget:
        raise UserError(f"budget {budget} is below what pruning can reach ({cost(high)} at ratio {high})")
    for _ in range(iterations):
        mid = (low + high) / 2
        if cost(mid) <= budget:
            high = mid
        else:
            low = mid
    return high
