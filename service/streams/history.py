"""The earlier frames a stream's detector reads (``history_frames``, docs/design.md section 5), kept by the replica
that ran them.

A model whose detector reads ``history_frames`` earlier frames gets, on each frame of a stream, the log power of
the frames before it in the stream, when this replica ran them and they are consecutive (``seq - 1``, ``seq - 2``,
...). Anything else (a gap, a frame run by another replica, a restarted replica, a stream evicted for memory) is an
absent earlier frame, which the detector reads as a single cube: the answer stays correct, only without history.
The tracker's state, which must survive replicas, lives in the ledger's database (service/streams/store.py); a
cube per frame does not belong there. Frames are kept as float16 log power (1 MB per ``small`` frame), in
least-recently-used order under ``max_bytes``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

Key = tuple[str, str]  # (tenant, stream id): a stream keeps its model for its life


class StreamHistory:
    """Per stream, its last frames' log power by ``seq``, within ``max_bytes`` over every stream."""

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = max_bytes
        self._streams: OrderedDict[Key, dict[int, np.ndarray]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def bytes(self) -> int:
        return self._bytes

    def earlier(self, key: Key, seq: int, n: int) -> list[np.ndarray | None]:
        """The ``n`` frames before ``seq`` (float32 log power, the latest first; None where not kept)."""
        with self._lock:
            frames = self._streams.get(key, {})
            if frames:
                self._streams.move_to_end(key)
            return [None if (kept := frames.get(seq - 1 - h)) is None else kept.astype(np.float32)
                    for h in range(n)]

    def keep(self, key: Key, seq: int, log_power: np.ndarray, n: int) -> None:
        """Keep frame ``seq`` of the stream, and of its earlier ones only what the next frame can read (``n``)."""
        frame = log_power.astype(np.float16)
        with self._lock:
            frames = self._streams.pop(key, {})
            frames[seq] = frame
            for old in [s for s in frames if s <= seq - n]:
                self._bytes -= frames.pop(old).nbytes
            self._bytes += frame.nbytes
            self._streams[key] = frames
            while self._bytes > self.max_bytes and self._streams:
                _, evicted = self._streams.popitem(last=False)
                self._bytes -= sum(f.nbytes for f in evicted.values())

    def forget(self, key: Key) -> None:
        """Drop a stream's frames (it was closed)."""
        with self._lock:
            self._bytes -= sum(f.nbytes for f in self._streams.pop(key, {}).values())
