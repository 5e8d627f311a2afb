"""Selection, surgery and pruned checkpoints (steps 2-3 of :mod:`models.slimming`): one global threshold over
the channel groups' importances, every member sliced to the kept indices, and the round trip checked."""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor, nn

from models.capabilities import dense_input_shapes
from models.channel_surgery import channel_table, slice_module
from models.checkpoint import Checkpoint
from models.compute import count_macs, count_params
from models.registry import create_model
from models.slimming.channels import ChannelGroup, trace_channels
from radar.errors import UserError

log = logging.getLogger(__name__)


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
