"""The DCA1000 UDP stream (radar.ti.udp, radar.ti.replay, radar.ti.live): packets placed by byte count, lost ones
zero-filled at their offsets and counted, reordered ones placed right, a truncated stream ends cleanly; and a
replay of OpenRadar's radar over loopback at 20 frames/s arrives whole."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from radar.ti.live import open_data_socket, receive_frames
from radar.ti.replay import replay, stream_packets
from radar.ti.udp import MAX_PAYLOAD, FrameAssembler, PacketError, pack_packet, unpack_packet

ROOT = Path(__file__).resolve().parents[3]
FRAME_BYTES = 256 * 4 * 128 * 2 * 2  # OpenRadar's radar: 256 chirps x 4 RX x 128 complex 16-bit samples


def frames_of_words(count: int, frame_bytes: int = FRAME_BYTES) -> list[bytes]:
    """Frames whose every 16-bit word says where it sits in the stream (word n holds n mod 65521, never 0)."""
    words = frame_bytes // 2
    return [((np.arange(i * words, (i + 1) * words) % 65521) + 1).astype("<u2").tobytes() for i in range(count)]


def assemble(packets, frame_bytes=FRAME_BYTES, window=4):
    assembler = FrameAssembler(frame_bytes, window=window)
    out = []
    for _, sequence, byte_count, payload in packets:
        out += assembler.add(sequence, byte_count, payload)
    return out + assembler.finish(), assembler.stats


def test_packets_round_trip_and_malformed_datagrams_are_refused():
    sequence, count, payload = unpack_packet(pack_packet(7, 123_456_789_012, b"\x01\x02\x03\x04"))
    assert (sequence, count, bytes(payload)) == (7, 123_456_789_012, b"\x01\x02\x03\x04")
    for bad in (b"", b"\x00" * 10, b"\x00" * 13):
        with pytest.raises(PacketError):
            unpack_packet(bad)


def test_a_whole_stream_comes_back_byte_for_byte():
    frames = frames_of_words(3)
    out, stats = assemble(stream_packets(frames))
    assert [bytes(f.data) for f in out] == frames and all(f.complete for f in out)
    assert stats.lost_packets == 0 and stats.frames == 3 and stats.packets == -(-3 * FRAME_BYTES // MAX_PAYLOAD)


def test_lost_packets_are_zero_filled_at_their_offsets_and_counted():
    frames = frames_of_words(3)
    packets = list(stream_packets(frames))
    dropped = {5, 360, 361, 400}  # 360 and 361 straddle the first frame's end (361 packets of 1456 bytes a frame)
    out, stats = assemble(p for p in packets if p[1] not in dropped)
    expected = bytearray(b"".join(frames))
    for _, sequence, count, payload in packets:
        if sequence in dropped:
            expected[count:count + len(payload)] = bytes(len(payload))
    assert b"".join(bytes(f.data) for f in out) == bytes(expected)  # no sample shifted
    assert stats.lost_packets == len(dropped) and stats.lost_bytes == len(dropped) * MAX_PAYLOAD
    assert stats.frames == 3 and stats.frames_with_loss == 2
    assert [f.lost_bytes > 0 for f in out] == [True, True, False]


def test_reordered_and_repeated_packets_are_placed_right():
    frames = frames_of_words(2)
    packets = list(stream_packets(frames))
    shuffled = packets[:10] + [packets[12], packets[10], packets[11]] + packets[13:]  # 12 overtakes 10 and 11
    shuffled.insert(20, packets[3])  # a repeat
    out, stats = assemble(shuffled)
    assert [bytes(f.data) for f in out] == frames
    assert stats.reordered_packets == 2 and stats.duplicate_packets == 1 and stats.lost_packets == 0


def test_a_truncated_stream_ends_cleanly_without_its_partial_frame():
    frames = frames_of_words(3)
    packets = list(stream_packets(frames))
    out, stats = assemble(packets[:-100])  # cut inside the third frame
    assert [bytes(f.data) for f in out] == frames[:2]
    assert stats.truncated_bytes > 0 and stats.frames == 2


def test_a_capture_joined_mid_frame_starts_at_the_next_frame():
    frames = frames_of_words(3)
    packets = [p for p in stream_packets(frames) if p[2] >= FRAME_BYTES + 10 * MAX_PAYLOAD]
    out, stats = assemble(packets)
    assert [bytes(f.data) for f in out] == frames[2:] and stats.skipped_leading_bytes > 0


def receive_replay(frames, rate, **options):
    sock = open_data_socket("127.0.0.1", 0)
    port = sock.getsockname()[1]
    assembler = FrameAssembler(FRAME_BYTES)
    received = []
    listener = threading.Thread(target=lambda: received.extend(
        receive_frames(sock, assembler, idle_timeout_s=1.0, start_timeout_s=10.0)))
    listener.start()
    try:
        sent = replay(frames, ("127.0.0.1", port), rate_fps=rate, frame_bytes=FRAME_BYTES, **options)
    finally:
        listener.join(timeout=30)
        sock.close()
    return received, assembler.stats, sent


def test_a_replay_over_loopback_at_20_frames_per_second_loses_nothing():
    iq = np.load(ROOT / "tests" / "fixtures" / "openradar" / "doppler_example_1.npy")
    real = iq.reshape(-1).astype("<i2").tobytes()  # a real frame's bytes, then counting words
    frames = [real] + frames_of_words(20)[1:]
    received, stats, sent = receive_replay(frames, 20.0)
    assert [bytes(f.data) for f in received] == frames
    assert stats.lost_packets == 0 and stats.frames == 20 and sent.frames == 20
    assert sent.seconds == pytest.approx(1.0, abs=0.25)  # paced at 20 frames/s


def test_a_replay_with_dropped_and_swapped_packets_over_loopback():
    frames = frames_of_words(4)
    received, stats, sent = receive_replay(frames, 50.0, drop=[7, 500], swap=[100])
    assert len(received) == 4 and sent.packets_dropped == 2
    assert stats.lost_packets == 2 and stats.reordered_packets == 1 and stats.lost_bytes == 2 * MAX_PAYLOAD
