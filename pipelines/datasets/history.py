"""Earlier frames of a frame's sequence in a store: what a detector that reads history gets beside the cube.

A store keeps each frame's ``sequence_id`` and ``frame_index`` (pipelines/datasets/store.py); the frame ``h + 1``
steps earlier in the same sequence is the history's entry ``h``. A frame at the start of its sequence, or whose
earlier frame was quarantined, has that entry absent (slot -1): the model then sees it as missing, exactly as a
single cube with no history.
"""

from __future__ import annotations

import numpy as np
import zarr

ABSENT = -1


def earlier_slots(root: zarr.Group, history: int) -> np.ndarray:
    """``(slots, history)`` int64: each slot's earlier frames, the latest first, ``ABSENT`` where there is none."""
    if history < 0:
        raise ValueError(f"history must be >= 0, got {history}")
    sequence = root["sequence_id"][:].astype(np.int64)
    index = root["frame_index"][:].astype(np.int64)
    valid = root["valid"][:].astype(bool)
    slot_of = {(s, i): slot for slot, (s, i, ok) in enumerate(zip(sequence, index, valid, strict=True)) if ok}
    out = np.full((len(sequence), history), ABSENT, np.int64)
    for slot, (s, i) in enumerate(zip(sequence, index, strict=True)):
        for h in range(history):
            out[slot, h] = slot_of.get((s, i - 1 - h), ABSENT)
    return out


def earlier_frames(inputs: zarr.Array, slots: np.ndarray) -> list[np.ndarray | None]:
    """The store's log power (R, A, D) dB, float32, of each of ``slots`` (one frame's row of :func:`earlier_slots`),
    None where ``ABSENT``."""
    return [None if s == ABSENT else inputs[int(s)].astype(np.float32) for s in slots]
