"""A capture sent as a DCA1000's raw-data UDP stream (radar/ti/udp.py's packets), paced at a frame rate: to test a
live capture without the board, on loopback or to another host.

The stream is the capture's frames back to back, cut into packets of :data:`radar.ti.udp.MAX_PAYLOAD` bytes as the
DCA1000 sends them (a packet may straddle two frames), numbered from 1 with the byte count before each. Packets are
spread evenly over each frame period. ``drop`` leaves packets out and ``swap`` sends a packet after its successor, by
sequence number, to exercise a receiver's loss and reordering handling.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from radar.ti.udp import MAX_PAYLOAD, pack_packet


@dataclass
class ReplayStats:
    frames: int = 0
    packets_sent: int = 0
    packets_dropped: int = 0
    bytes_sent: int = 0
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {"frames": self.frames, "packets_sent": self.packets_sent, "packets_dropped": self.packets_dropped,
                "bytes_sent": self.bytes_sent, "seconds": round(self.seconds, 3),
                "frames_per_s": round(self.frames / self.seconds, 2) if self.seconds > 0 else None}


def stream_packets(frames: Iterable[bytes], *, payload_bytes: int = MAX_PAYLOAD
                   ) -> Iterator[tuple[int, int, int, bytes]]:
    """(frame index at the packet's end, sequence number, byte count before it, payload) over the frames' bytes
    back to back; the last packet may be short."""
    if payload_bytes <= 0 or payload_bytes % 2:
        raise ValueError(f"payload_bytes must be a positive even number, got {payload_bytes}")
    carry, sent, sequence, index = b"", 0, 1, 0
    for index, frame in enumerate(frames):
        data = carry + bytes(frame)
        whole = len(data) - len(data) % payload_bytes
        view = memoryview(data)
        for at in range(0, whole, payload_bytes):
            yield index, sequence, sent, bytes(view[at:at + payload_bytes])
            sent, sequence = sent + payload_bytes, sequence + 1
        carry = data[whole:]
    if carry:
        yield index, sequence, sent, carry


def _swapped(packets: Iterator[tuple[int, int, int, bytes]], swap: frozenset[int]
             ) -> Iterator[tuple[int, int, int, bytes]]:
    """Packet ``n`` in ``swap`` goes out after packet ``n + 1``."""
    held = None
    for packet in packets:
        if held is not None:
            yield packet
            yield held
            held = None
        elif packet[1] in swap:
            held = packet
        else:
            yield packet
    if held is not None:
        yield held


def replay(frames: Iterable[bytes], to: tuple[str, int], *, rate_fps: float, frame_bytes: int,
           drop: Iterable[int] = (), swap: Iterable[int] = (), payload_bytes: int = MAX_PAYLOAD,
           sock: socket.socket | None = None) -> ReplayStats:
    """Send ``frames`` (each ``frame_bytes``) to ``to`` as DCA1000 data packets at ``rate_fps`` frames a second."""
    if not rate_fps > 0:
        raise ValueError(f"rate must be > 0 frames/s, got {rate_fps}")
    per_packet_s = 1.0 / rate_fps * payload_bytes / frame_bytes
    drop, stats = frozenset(drop), ReplayStats()
    own = sock is None
    sock = sock or socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start = time.perf_counter()
    try:
        for frame_index, sequence, byte_count, payload in _swapped(
                stream_packets(frames, payload_bytes=payload_bytes), frozenset(swap)):
            stats.frames = max(stats.frames, frame_index + 1)
            if sequence in drop:
                stats.packets_dropped += 1
                continue
            ahead = start + (byte_count // payload_bytes) * per_packet_s - time.perf_counter()
            if ahead > 0.001:
                time.sleep(ahead)
            sock.sendto(pack_packet(sequence, byte_count, payload), to)
            stats.packets_sent += 1
            stats.bytes_sent += len(payload)
    finally:
        if own:
            sock.close()
    stats.seconds = time.perf_counter() - start
    return stats
