"""What a sharded job's stage reads and writes per shard: the :class:`SourceSpec` it reopens, the
:class:`FrameSlot` of each frame, the :class:`ShardJob` payload, and :func:`fill_shard` (the shard's
buffers, bad frames quarantined).
Shared by :mod:`pipelines.datasets.preprocess` and :mod:`pipelines.inference.segment_batch`; the runner is
:mod:`pipelines.datasets.sharded_job`."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pipelines.datasets.sharded_store import Sharded
from radar.errors import DataError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SourceSpec:
    """Where a stage gets its frames: enough to reopen the source inside a Ray worker."""

    kind: str  # the job's source kinds ("sim", "recording", "store", ...)
    path: str | None  # absolute; None for the simulator
    preset: str
    seed: int | None = None  # the simulator's scene seed (preprocessing records it for every source)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        if self.seed is None:
            del data["seed"]
        return data


@dataclass(frozen=True)
class FrameSlot:
    """One frame of the job's source and the store slot it takes."""

    slot: int
    sequence_id: int  # index into the store's ``sequences`` attribute
    sequence: str
    index: int  # frame index within its sequence

    def slot_arrays(self) -> dict[str, int]:
        """What the store records in this slot, whether or not the frame turns out good."""
        return {"sequence_id": self.sequence_id, "frame_index": self.index}


@dataclass(frozen=True)
class ShardJob:
    """The payload of one shard: where to write and what each of its slots holds."""

    store: str
    layout: Sharded
    source: SourceSpec
    shard: int
    frames: tuple[FrameSlot, ...]  # one per slot of the shard, in slot order


def fill_shard(job: ShardJob, frames: Iterable[tuple[FrameSlot, Any]],
               encode: Callable[[Any], dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """Buffers of every array of ``job``'s shard, and its quarantined frames.

    ``frames`` yields each slot with its frame, or with the DataError that reading it raised; ``encode``
    returns a frame's arrays or raises ValueError (DataError is one). A bad frame is quarantined: its slot
    keeps the fill values but for :meth:`FrameSlot.slot_arrays`, ``valid`` stays 0, the reason is kept and
    the shard carries on.
    """
    buffers = job.layout.empty_shard(job.shard)
    start, _ = job.layout.shard_bounds(job.shard)
    quarantined = []
    for ref, frame in frames:
        k = ref.slot - start
        for name, value in ref.slot_arrays().items():
            buffers[name][k] = value
        try:
            if isinstance(frame, DataError):
                raise frame
            encoded = encode(frame)
        except ValueError as exc:
            log.warning("quarantined %s/%d: %s", ref.sequence, ref.index, exc)
            quarantined.append({"frame": ref.slot, "sequence": ref.sequence, "index": ref.index, "reason": str(exc)})
            continue
        for name, value in encoded.items():
            buffers[name][k] = value
        buffers["valid"][k] = 1
    return buffers, quarantined
