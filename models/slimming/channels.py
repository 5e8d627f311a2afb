"""Channel groups (step 2 of :mod:`models.slimming`): a model described as sets of channels that are kept or
removed together, by one tracer per architecture family (:data:`TRACERS`, named by a class's ``channel_tracer``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from models.channel_surgery import out_size
from models.detector.bifpn import BiFPNNeck
from models.detector.efficientnet import EfficientNetBackbone
from models.layers import SeparableConv2d
from models.segmenter.spvcnn import FUSE_AFTER_DECODER_STAGE


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
