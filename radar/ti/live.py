"""Receiving a DCA1000's raw-data UDP stream: a bound socket, and frames as they complete (radar/ti/udp.py), within
bounds: at most ``max_frames`` frames and ``max_seconds`` seconds, ending when no packet came for ``idle_timeout_s``
(the radar stopped, or a replay ended)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

from radar.ti.udp import DATA_PORT, AssembledFrame, FrameAssembler, PacketError, unpack_packet

RECEIVE_BUFFER = 8 * 1024 * 1024  # bytes asked of the kernel for the socket (the system may grant less)
DATAGRAM_MAX = 65_536  # any UDP datagram, so that one longer than a DCA1000 packet (1466 bytes) is seen whole


def open_data_socket(host: str = "0.0.0.0", port: int = DATA_PORT, *, buffer_bytes: int = RECEIVE_BUFFER
                     ) -> socket.socket:
    """A UDP socket bound to ``host:port`` with a receive buffer of about ``buffer_bytes`` (port 0: any free)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for option in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
            if option is None:
                continue
            try:
                sock.setsockopt(socket.SOL_SOCKET, option, buffer_bytes)
                break
            except OSError:  # SO_RCVBUFFORCE needs CAP_NET_ADMIN; SO_RCVBUF is capped by net.core.rmem_max
                continue
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def receive_frames(sock: socket.socket, assembler: FrameAssembler, *, max_frames: int | None = None,
                   max_seconds: float | None = None, idle_timeout_s: float = 2.0, start_timeout_s: float = 30.0
                   ) -> Iterator[AssembledFrame]:
    """Frames of the stream arriving on ``sock`` until a bound is reached (``start_timeout_s`` without a first
    packet, ``idle_timeout_s`` without the next); then the frames still open (zero-filled where packets were lost;
    a last frame cut short is dropped and counted)."""
    deadline = None if max_seconds is None else time.monotonic() + max_seconds
    emitted = 0
    buffer = bytearray(DATAGRAM_MAX)
    started = False
    while max_frames is None or emitted < max_frames:
        wait = idle_timeout_s if started else start_timeout_s
        if deadline is not None:
            wait = min(wait, deadline - time.monotonic())
            if wait <= 0:
                break
        sock.settimeout(wait)
        try:
            size = sock.recv_into(buffer)
        except TimeoutError:
            break
        started = True
        try:
            sequence, byte_count, payload = unpack_packet(memoryview(buffer)[:size])
        except PacketError:
            assembler.stats.malformed_packets += 1
            continue
        for frame in assembler.add(sequence, byte_count, payload):
            yield frame
            emitted += 1
            if max_frames is not None and emitted >= max_frames:
                return
    for frame in assembler.finish():
        if max_frames is not None and emitted >= max_frames:
            return
        yield frame
        emitted += 1
