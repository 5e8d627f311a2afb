"""A DCA1000 stream under hostile or unlucky packets: sequence numbers that wrap at 2^32, a spoofed byte count near
2^48, datagrams larger than any DCA1000 packet, and ``radarseg capture`` surviving a bad frame (zero-filled or dropped
as --bad-frames says, counted, every good frame kept)."""

from __future__ import annotations

import json
import socket
import threading

import numpy as np
import pytest

from pipelines.cli import main
from radar.ti.dca1000 import CaptureFormat, encode_frame
from radar.ti.live import open_data_socket, receive_frames
from radar.ti.replay import replay, stream_packets
from radar.ti.udp import FrameAssembler, PacketError, pack_packet, unpack_packet
from tests.radar.ti.test_capture import SMALL, _profile, _simulated_frames
from tests.radar.ti.test_udp import FRAME_BYTES, assemble, frames_of_words


def test_sequence_numbers_that_wrap_at_2_32_lose_nothing():
    frames = frames_of_words(3)
    start = 2**32 - 100
    packets = [(i, (sequence + start) % 2**32, count, payload)
               for i, sequence, count, payload in stream_packets(frames)]
    out, stats = assemble(packets)
    assert [bytes(f.data) for f in out] == frames
    assert stats.lost_packets == 0  # it said 4,294,966,750


def test_a_spoofed_first_byte_count_near_2_48_is_outvoted_by_the_stream():
    frames = frames_of_words(6)
    packets = [(0, 999, 2**48 - 4096, b"\0\0" * 8), *stream_packets(frames)]
    out, stats = assemble(packets)
    assert len(out) >= 5 and [bytes(f.data) for f in out[-5:]] == frames[-5:]  # every frame was lost before
    assert stats.stray_packets >= 1 and stats.resyncs == 1


def test_datagrams_larger_than_a_dca1000_packet_are_malformed():
    with pytest.raises(PacketError, match="longer than a DCA1000 data packet"):
        unpack_packet(pack_packet(1, 0, bytes(60_000)))
    sock = open_data_socket("127.0.0.1", 0)
    assembler = FrameAssembler(FRAME_BYTES)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.sendto(pack_packet(1, 0, bytes(60_000)), sock.getsockname())
        list(receive_frames(sock, assembler, idle_timeout_s=0.5, start_timeout_s=10))
    sock.close()
    assert assembler.stats.malformed_packets == 1 and assembler.stats.packets == 0


@pytest.mark.parametrize("policy", ["zero", "drop"])
def test_capture_survives_a_bad_frame_and_keeps_every_good_one(tmp_path, capsys, policy):
    """Five frames, the third all 0x8000 words: it aborted the capture (exit 2, two frames written)."""
    profile_path = tmp_path / "p.json"
    profile_path.write_text(json.dumps(SMALL))
    fmt = CaptureFormat()
    good = _simulated_frames(_profile(), fmt, n=5)
    words = [encode_frame(frame, fmt).astype("<u2").tobytes() for frame in good]
    words[2] = np.full(len(words[2]) // 2, 0x8000, "<u2").tobytes()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    out = tmp_path / "c.bin"
    sender = threading.Timer(1.5, replay, args=(words, ("127.0.0.1", port)),
                             kwargs={"rate_fps": 50.0, "frame_bytes": len(words[0])})
    sender.start()
    try:
        status = main(["capture", "--profile", str(profile_path), "--host", "127.0.0.1", "--port", str(port),
                       "--out", str(out), "--max-frames", "5", "--idle-timeout", "1", "--start-timeout", "20",
                       "--bad-frames", policy])
    finally:
        sender.join()
    assert status == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["bad_frames"] == 1 and summary["bad_frame_indices"] == [2]
    written = out.read_bytes()
    kept = [w for i, w in enumerate(words) if i != 2]
    expected = kept[:2] + [bytes(len(words[2]))] + kept[2:] if policy == "zero" else kept
    assert written == b"".join(expected)
