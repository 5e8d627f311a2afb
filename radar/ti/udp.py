"""The DCA1000's raw-data UDP stream: its packets, and frames reassembled from them by byte offset.

Each data packet (DCA1000EVM user guide; the DCA1000 CLI and OpenRadar's ``mmwave.dataloader.DCA1000`` read them
so): a 4-byte little-endian sequence number (1 for the first packet of a recording, +1 a packet), a 6-byte
little-endian byte count (the stream's bytes sent before this packet), then up to :data:`MAX_PAYLOAD` bytes of ADC
words, sent to the host's data port (:data:`DATA_PORT`).

:class:`FrameAssembler` puts every payload where its byte count says: a lost packet leaves its bytes zero (never a
shift of the samples after it), a late (reordered) packet lands in its place as long as its frame is still open, a
repeated packet is counted and ignored. Frames leave in order, whole or zero-filled, once they are complete or the
stream has moved :attr:`FrameAssembler.window` frames past them; memory is bounded by that window.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field

DATA_PORT = 4098  # the host's UDP port for the DCA1000's raw data
MAX_PAYLOAD = 1456  # ADC bytes in a full data packet
HEADER = struct.Struct("<I")  # sequence number; the 6-byte byte count follows
HEADER_BYTES = 10
MAX_BYTE_COUNT = 1 << 48
SEQUENCE_SPAN = 1 << 32  # sequence numbers wrap here
RESYNC_PACKETS = 16  # packets in a row far from the stream's place that move it there (a spoofed or stale anchor)


class PacketError(ValueError):
    """A datagram that is not a DCA1000 data packet."""


def pack_packet(sequence: int, byte_count: int, payload: bytes) -> bytes:
    """One data packet: sequence number, byte count before it, payload."""
    if not 0 <= sequence < 1 << 32 or not 0 <= byte_count < MAX_BYTE_COUNT:
        raise ValueError(f"sequence {sequence} or byte count {byte_count} out of range")
    return HEADER.pack(sequence) + byte_count.to_bytes(6, "little") + bytes(payload)


def unpack_packet(datagram: bytes | memoryview) -> tuple[int, int, memoryview]:
    """(sequence number, byte count, payload) of one datagram; PacketError if it is shorter than a header or its
    payload is not whole 16-bit words."""
    view = memoryview(datagram)
    if len(view) > HEADER_BYTES + MAX_PAYLOAD:
        raise PacketError(f"a {len(view)}-byte datagram is longer than a DCA1000 data packet (at most "
                          f"{HEADER_BYTES + MAX_PAYLOAD} bytes)")
    if len(view) <= HEADER_BYTES or (len(view) - HEADER_BYTES) % 2:
        raise PacketError(f"a {len(view)}-byte datagram is no DCA1000 data packet (10-byte header, then 16-bit words)")
    (sequence,) = HEADER.unpack_from(view, 0)
    return sequence, int.from_bytes(view[4:HEADER_BYTES], "little"), view[HEADER_BYTES:]


@dataclass
class AssembledFrame:
    """One frame of the stream: ``index`` (byte offset // frame bytes), its bytes, and how many of them were lost
    (left zero)."""

    index: int
    data: bytearray
    lost_bytes: int

    @property
    def complete(self) -> bool:
        return self.lost_bytes == 0


@dataclass
class StreamStats:
    """What the stream delivered and lost."""

    packets: int = 0
    duplicate_packets: int = 0
    late_packets: int = 0  # arrived after their frame had left (zero-filled there)
    reordered_packets: int = 0  # arrived after a packet with a higher sequence number, placed right
    malformed_packets: int = 0
    stray_packets: int = 0  # byte counts more than max_gap_frames from the stream's place: set aside
    resyncs: int = 0  # RESYNC_PACKETS strays in a row moved the stream to them (its open frames were lost)
    unique_packets: int = 0  # of the stream since its last resync, repeats aside
    first_sequence: int | None = None  # sequence numbers unwrapped (they wrap at 2^32)
    last_sequence: int | None = None
    frames: int = 0
    frames_with_loss: int = 0
    lost_bytes: int = 0
    skipped_leading_bytes: int = 0  # of a frame begun before the capture started
    truncated_bytes: int = 0  # received of a last frame the stream cut short (that frame is dropped)
    missing_frames: list[int] = field(default_factory=list)  # indices of frames no packet of which arrived

    @property
    def lost_packets(self) -> int:
        """Sequence numbers never received between the first and the last one seen."""
        if self.first_sequence is None:
            return 0
        return max(0, self.last_sequence - self.first_sequence + 1 - self.unique_packets)

    def to_dict(self) -> dict:
        return {"packets": self.packets, "lost_packets": self.lost_packets,
                "duplicate_packets": self.duplicate_packets, "reordered_packets": self.reordered_packets,
                "late_packets": self.late_packets, "malformed_packets": self.malformed_packets,
                "stray_packets": self.stray_packets, "resyncs": self.resyncs,
                "frames": self.frames, "frames_with_loss": self.frames_with_loss, "lost_bytes": self.lost_bytes,
                "lost_frames": len(self.missing_frames), "skipped_leading_bytes": self.skipped_leading_bytes,
                "truncated_bytes": self.truncated_bytes}


class FrameAssembler:
    """Frames of ``frame_bytes`` from packets placed by byte count (see the module docstring)."""

    def __init__(self, frame_bytes: int, *, window: int = 4, recent: int = 65_536, max_gap_frames: int = 1000):
        if frame_bytes <= 0 or frame_bytes % 2:
            raise ValueError(f"frame_bytes must be a positive even number, got {frame_bytes}")
        self.frame_bytes = frame_bytes
        self.window = max(1, window)
        self.max_gap_frames = max_gap_frames
        self._first_index = 0
        self.stats = StreamStats()
        self._open: dict[int, list] = {}  # index -> [data, filled mask per 2-byte word, bytes received]
        self._next = None  # the next frame index to leave
        self._seen: deque[int] = deque(maxlen=recent)
        self._seen_set: set[int] = set()
        self._strays = 0  # far packets in a row

    def _first_packet(self, byte_count: int) -> None:
        index, rest = divmod(byte_count, self.frame_bytes)
        if index == 0:  # the recording began while we listened (its first packets may come out of order)
            rest = 0
        self._next = index + (1 if rest else 0)  # a frame begun before the capture started is not one of ours
        self._first_index = self._next
        self.stats.skipped_leading_bytes = (self.frame_bytes - rest) % self.frame_bytes if rest else 0

    def _unwrap(self, sequence: int) -> int:
        """The sequence number counted past 2^32: the one of its wraps nearest the last one seen."""
        last = self.stats.last_sequence
        if last is None:
            return sequence
        base = last - last % SEQUENCE_SPAN + sequence
        return min((base - SEQUENCE_SPAN, base, base + SEQUENCE_SPAN), key=lambda s: abs(s - last))

    def _note_sequence(self, sequence: int) -> bool:
        """False for a repeated packet."""
        sequence = self._unwrap(sequence)
        if sequence in self._seen_set:
            self.stats.duplicate_packets += 1
            return False
        if len(self._seen) == self._seen.maxlen:
            self._seen_set.discard(self._seen[0])
        self._seen.append(sequence)
        self._seen_set.add(sequence)
        s = self.stats
        s.unique_packets += 1
        if s.last_sequence is not None and sequence < s.last_sequence:
            s.reordered_packets += 1
        s.first_sequence = sequence if s.first_sequence is None else min(s.first_sequence, sequence)
        s.last_sequence = sequence if s.last_sequence is None else max(s.last_sequence, sequence)
        return True

    def add(self, sequence: int, byte_count: int, payload: bytes | memoryview) -> list[AssembledFrame]:
        """Place one packet; the frames that can leave now, in order."""
        self.stats.packets += 1
        if self._next is not None and abs(byte_count // self.frame_bytes - self._next) > self.max_gap_frames:
            if not self._stray():
                return []
        else:
            self._strays = 0
        if not self._note_sequence(sequence):
            return []
        if self._next is None:
            self._first_packet(byte_count)
        payload = memoryview(payload)
        offset, end = byte_count, byte_count + len(payload)
        late = False
        while offset < end:
            index, start = divmod(offset, self.frame_bytes)
            stop = min(self.frame_bytes, start + end - offset)
            if index < self._next:
                late = late or offset >= self._next_start_bytes()
            else:
                entry = self._open.get(index)
                if entry is None:
                    entry = self._open[index] = [bytearray(self.frame_bytes), bytearray(self.frame_bytes // 2), 0]
                data, filled = entry[0], entry[1]
                data[start:stop] = payload[offset - byte_count:offset - byte_count + stop - start]
                entry[2] += 2 * filled.count(0, start // 2, stop // 2)  # bytes newly filled
                filled[start // 2:stop // 2] = b"\x01" * (stop // 2 - start // 2)
            offset += stop - start
        if late:
            self.stats.late_packets += 1
        return self._leave(newest=(end - 1) // self.frame_bytes)

    def _stray(self) -> bool:
        """A byte count far from the stream's place: set aside and counted; True when it is the RESYNC_PACKETS-th
        in a row, and the stream moves to it (a spoofed first packet, or a radar restarted: its open frames lost)."""
        self.stats.stray_packets += 1
        self._strays += 1
        if self._strays < RESYNC_PACKETS:
            return False
        s = self.stats
        s.lost_bytes += sum(self.frame_bytes - entry[2] for entry in self._open.values())
        s.resyncs, s.first_sequence, s.last_sequence, s.unique_packets = s.resyncs + 1, None, None, 0
        self._open.clear()
        self._seen.clear()
        self._seen_set.clear()
        self._next, self._strays = None, 0
        return True

    def _next_start_bytes(self) -> int:
        """Byte offset of the first frame of ours (bytes before it belong to a frame begun before the capture)."""
        return self._first_index * self.frame_bytes

    def _leave(self, newest: int, *, flush: bool = False) -> list[AssembledFrame]:
        """Frames from the next one on that are whole, or settled: ``window`` frames behind ``newest``, or the
        stream ended (``flush``). The stream's last frame leaves on flush only if its last word arrived."""
        out = []
        while self._next is not None and self._next <= newest:
            index = self._next
            settled = flush or newest - index >= self.window
            entry = self._open.get(index)
            if entry is None:
                if not settled:
                    break
                self.stats.missing_frames.append(index)
            else:
                data, filled, received = entry
                missing = self.frame_bytes - received
                if missing and not settled:
                    break
                self._open.pop(index)
                if flush and index == newest and not filled[-1]:
                    self.stats.truncated_bytes += received  # cut mid-frame
                else:
                    out.append(self._emit(index, data, missing))
            self._next += 1
        return out

    def _emit(self, index: int, data: bytearray, missing: int) -> AssembledFrame:
        self.stats.frames += 1
        if missing:
            self.stats.frames_with_loss += 1
            self.stats.lost_bytes += missing
        return AssembledFrame(index, data, missing)

    def finish(self) -> list[AssembledFrame]:
        """The stream ended: every frame still open leaves (zero-filled where packets were lost); the last one only
        when whole (a stream cut mid-frame loses that frame, counted in ``lost_bytes``)."""
        if not self._open:
            return []
        return self._leave(newest=max(self._open), flush=True)
