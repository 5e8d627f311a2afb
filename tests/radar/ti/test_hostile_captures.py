"""Hostile capture files refused before they cost memory or time: a mmWave Studio Raw file of tiny packets (its index
built without a Python object per packet), packets of ever-changing lengths, and a sparse .npy whose header matches
its size but not the profile (checked before the file is read)."""

from __future__ import annotations

import json
import resource
import time

import numpy as np
import pytest

from pipelines.cli import main
from radar.adc import adc_shape
from radar.errors import DataError
from radar.ti.capture import MIN_PACKET, Capture
from radar.ti.capture_writer import write_dca1000, write_studio_raw
from radar.ti.dca1000 import CaptureFormat
from tests.radar.ti.test_capture import SMALL, _profile, _simulated_frames


def _packet(sequence: int, position: int, payload: bytes) -> bytes:
    return sequence.to_bytes(4, "little") + len(payload).to_bytes(4, "little") + position.to_bytes(6, "little") + \
        payload


def _peak_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def test_a_raw_file_of_tiny_packets_is_refused_at_once(tmp_path):
    """64 MiB of 16-byte packets: 27 s and 1,021 MB with a Python object per packet."""
    packet = np.frombuffer(_packet(1, 0, b"\0\0"), np.uint8)
    path = tmp_path / "adc_data_Raw_0.bin"
    np.tile(packet, (64 << 20) // packet.size).tofile(path)
    before, started = _peak_kib(), time.process_time()
    with pytest.raises(DataError, match=f"2 payload bytes, a DCA1000 packet carries at least {MIN_PACKET}"):
        Capture(path, _profile())
    assert time.process_time() - started < 2.0
    assert _peak_kib() - before < 100_000


def test_packets_of_ever_changing_lengths_are_refused(tmp_path):
    payloads = [bytes(MIN_PACKET + (i % 2)) for i in range(20_000)]
    stream, position = bytearray(), 0
    for number, payload in enumerate(payloads, start=1):
        stream += _packet(number, position, payload)
        position += len(payload)
    path = tmp_path / "x_Raw_0.bin"
    path.write_bytes(bytes(stream))
    started = time.process_time()
    with pytest.raises(DataError, match="lengths change more than"):
        Capture(path, _profile())
    assert time.process_time() - started < 5.0


def test_many_packets_index_as_numpy_rows_and_read_back(tmp_path):
    """A Studio capture of many frames (lengths change only at the stream's end), split over files, with a lost
    packet: read back word for word."""
    profile, fmt = _profile(), CaptureFormat()
    frames = _simulated_frames(profile, fmt, n=40)
    files = write_studio_raw(tmp_path / "adc_data", frames, fmt, payload=200, max_file_bytes=30_000,
                             drop=frozenset({7}))
    capture = Capture(files[0], profile)
    assert len(capture) == 40 and len(files) >= 3
    assert capture._packets.table.dtype == np.int64
    np.testing.assert_array_equal(capture.frame(39), frames[39])
    words = capture.words(0)
    assert capture.lost_bytes == 200 and np.all(words[600:700] == 0)


def test_process_adc_checks_an_npy_header_against_the_profile_before_reading(tmp_path, capsys):
    """A sparse 16 GiB .npy whose header (2**31,) complex64 matches its size: read whole (4 GB at 50 s) before."""
    path = tmp_path / "adc.npy"
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1, np.complex64))
    header["shape"] = (2**31,)
    with path.open("wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        fh.truncate(fh.tell() + 2**31 * 8)
    profile = tmp_path / "p.json"
    profile.write_text(json.dumps(SMALL))
    before, started = _peak_kib(), time.process_time()
    assert main(["process-adc", str(path), "--profile", str(profile), "--out", str(tmp_path / "c.npy")]) == 2
    assert f"have shape {adc_shape(_profile(), 'sck')}, got (2147483648,)" in capsys.readouterr().err
    assert time.process_time() - started < 2.0 and _peak_kib() - before < 100_000


def test_an_offset_binary_capture_is_named_not_called_clipping(tmp_path, capsys):
    """Offset-binary words read as two's complement sit at both ends of full scale: refused naming --offset-binary
    (it was a clipping warning and exit 0); read with --offset-binary, the same file gives the frame."""
    profile_path = tmp_path / "p.json"
    profile_path.write_text(json.dumps(SMALL))
    offset = CaptureFormat(offset_binary=True)
    frames = _simulated_frames(_profile(), offset)
    path = tmp_path / "adc_data.bin"
    write_dca1000(path, frames, offset)
    command = ["process-adc", str(path), "--profile", str(profile_path), "--out", str(tmp_path / "c.npy")]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert "offset-binary words read as two's complement" in err and "--offset-binary" in err
    assert "clipped" not in err
    assert main([*command, "--offset-binary"]) == 0
    np.testing.assert_array_equal(Capture(path, _profile(), offset).frame(0), frames[0])
