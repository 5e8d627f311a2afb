"""Capture files of a TI radar as ADC frames, memory-mapped (a file is never read whole):

- the DCA1000's ``adc_data.bin`` (the DCA1000 CLI, or mmWave Studio's post-processed file): the frames' words back
  to back (radar/ti/dca1000.py);
- mmWave Studio's ``PREFIX_Raw_0.bin``, ``PREFIX_Raw_1.bin``, ...: the DCA1000's packets as recorded, split into files
  by size (a frame may straddle two files). Each packet: 4-byte sequence number, 4-byte payload length, 6-byte byte
  count (bytes of the stream before this packet), all little-endian, then the payload (as OpenRadar's
  ``mmwave.dataloader.parse_raw_adc`` reads them). Payloads go where their byte count puts them; bytes of lost packets
  read as zero and are counted.

A file whose size does not fit the profile is refused with one line: the bytes found, the bytes a frame takes and
the likely cause. A partial last frame (a capture stopped mid-frame) is refused too unless ``partial="skip"``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from radar.errors import DataError
from radar.profiles import RadarProfile
from radar.ti.dca1000 import CaptureFormat, FrameGeometry, decode_frame

RAW_FILE = re.compile(r"^(?P<prefix>.*)_Raw_(?P<index>\d+)\.bin$")
PACKET_HEADER = 14  # bytes: sequence number (4), payload length (4), byte count (6)
MAX_PACKET = 65_536
# A DCA1000 packet carries 1456 payload bytes by default, all of one length but a file's last: a file of 16-byte
# packets would index a million packets for 16 MiB. Lengths change at most MAX_LENGTH_CHANGES times in a file.
MIN_PACKET = 64
MAX_LENGTH_CHANGES = 4096
_FIRST_RUN, _MAX_RUN = 64, 1 << 16  # packets of one length looked for at once, doubled while they keep coming


def _likely_cause(size: int, geometry: FrameGeometry) -> str:
    """What configuration a capture of ``size`` bytes would fit instead (other ADC kind, RX or chirp count)."""
    g = geometry
    if size % 2:
        return "an odd number of bytes: not 16-bit words, or a damaged file"
    other = FrameGeometry(g.chirps, g.rx, g.samples, not g.complex_adc)
    if size % other.bytes == 0:
        return (f"a whole number of {'real' if g.complex_adc else 'complex'}-ADC frames: was the ADC "
                f"{'real (adcCfg ... 0)' if g.complex_adc else 'complex'}?")
    for rx in (1, 2, 3, 4):
        if rx != g.rx and size % FrameGeometry(g.chirps, rx, g.samples, g.complex_adc).bytes == 0:
            return f"whole frames of {rx} RX: does channelCfg enable {rx} RX, not {g.rx}?"
    return "a capture of another configuration (samples, chirps, TX or RX), or a truncated file"


def _check_size(path: Path, size: int, geometry: FrameGeometry, partial: str, what: str) -> int:
    """Whole frames in ``size`` bytes; DataError (one line) when they do not fit the profile."""
    frame = geometry.bytes
    shape = (f"{geometry.chirps} chirps x {geometry.rx} RX x {geometry.samples} samples x "
             f"{'2 (I/Q) x ' if geometry.complex_adc else ''}2 bytes = {frame} bytes a frame")
    if size < frame:
        raise DataError(path, f"{what} holds {size} bytes, less than one frame ({shape}); likely cause: "
                              f"{_likely_cause(size, geometry)}")
    whole, rest = divmod(size, frame)
    if rest and partial != "skip":
        hint = _likely_cause(size, geometry)
        raise DataError(path, f"{what} holds {size} bytes: {whole} whole frames and {rest} bytes of a partial last "
                              f"frame ({shape}); likely cause: the capture stopped mid-frame (read the whole frames "
                              f"with --skip-partial), or {hint}")
    return whole


class Capture:
    """The frames of one capture, for one radar profile: ``len()``, ``frame(i)`` (chirps, rx, samples) complex64 in the
    ADC chain's ``"ti"`` layout, iteration. ``lost_bytes``: bytes zero-filled for lost packets (read so far)."""

    def __init__(self, path: str | Path, profile: RadarProfile, fmt: CaptureFormat | None = None, *,
                 partial: str = "refuse"):
        self.path = Path(path)
        self.profile = profile
        self.format = fmt or CaptureFormat.of_profile(profile)
        self.geometry = FrameGeometry.of_profile(profile, self.format)
        problem = self.geometry.layout_problem(self.format)
        if problem:
            raise DataError(self.path, f"{self.format.describe()}: {problem}")
        if not self.path.is_file():
            raise DataError(self.path, "no such capture file")
        self.lost_bytes = 0
        match = RAW_FILE.match(self.path.name)
        self.studio = match is not None
        if self.studio:
            self._packets = _StudioPackets(self.path, match.group("prefix"))
            size, what = self._packets.stream_bytes, f"the packet stream of {len(self._packets.files)} Raw file(s)"
        else:
            size, what = self.path.stat().st_size, "the capture"
            self._words = np.memmap(self.path, dtype="<u2", mode="r", shape=(size // 2,)) if size >= 2 else None
        self.n_frames = _check_size(self.path, size, self.geometry, partial, what)

    def __len__(self) -> int:
        return self.n_frames

    def words(self, index: int) -> np.ndarray:
        """Frame ``index``'s uint16 words, as stored."""
        if not 0 <= index < self.n_frames:
            raise DataError(self.path, f"frame {index} out of range: the capture holds {self.n_frames} whole frames")
        n = self.geometry.words
        if self.studio:
            data, lost = self._packets.read(index * 2 * n, 2 * n)
            self.lost_bytes += lost
            return np.frombuffer(data, dtype="<u2")
        return np.asarray(self._words[index * n:(index + 1) * n])

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as (chirps, rx, samples) complex64."""
        return decode_frame(self.words(index), self.format, self.geometry)

    def __iter__(self) -> Iterator[np.ndarray]:
        for index in range(self.n_frames):
            yield self.frame(index)


class _StudioPackets:
    """Index of the packets of ``PREFIX_Raw_0.bin``, ``PREFIX_Raw_1.bin``, ... (headers only are read)."""

    def __init__(self, first: Path, prefix: str):
        self.files = []
        index = 0
        while (first.parent / f"{prefix}_Raw_{index}.bin").is_file():
            self.files.append(first.parent / f"{prefix}_Raw_{index}.bin")
            index += 1
        if not self.files or self.files[0].name != f"{prefix}_Raw_0.bin" or first not in self.files:
            raise DataError(first, f"a mmWave Studio capture starts at {prefix}_Raw_0.bin, which is missing")
        self.maps = [np.memmap(f, dtype=np.uint8, mode="r") if f.stat().st_size else np.zeros(0, np.uint8)
                     for f in self.files]
        tables = [self._headers(number, data) for number, data in enumerate(self.maps)]
        # (file, payload offset, length, stream position) of every packet, by stream position
        table = tables[0] if len(tables) == 1 else np.concatenate(tables)
        if table.shape[0] > 1 and (np.diff(table[:, 3]) < 0).any():
            table = table[np.argsort(table[:, 3], kind="stable")]
        self.table = table
        self.stream_bytes = int((self.table[:, 3] + self.table[:, 2]).max(initial=0))

    def _refuse(self, number: int, message: str) -> DataError:
        return DataError(self.files[number], message)

    def _header_fields(self, data: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Payload lengths and byte counts of the packet headers at ``starts`` (numpy gathers, little-endian)."""
        lengths = data[starts[:, None] + np.arange(4, 8)].copy().view("<u4")[:, 0].astype(np.int64)
        counts = np.zeros((starts.size, 8), np.uint8)
        counts[:, :6] = data[starts[:, None] + np.arange(8, 14)]
        return lengths, counts.view("<u8")[:, 0].astype(np.int64)

    def _headers(self, number: int, data: np.ndarray) -> np.ndarray:
        """(packets, 4) int64 rows of one file: runs of packets of one payload length are found with numpy (the
        headers of a run read at once), so no Python object is made per packet."""
        pos, size, window, changes, count = 0, data.size, _FIRST_RUN, 0, 0
        # as many rows as packets of MIN_PACKET bytes could fill the file: pages are touched only as rows are written
        rows = np.empty((size // (PACKET_HEADER + MIN_PACKET) + 1, 4), np.int64)
        while pos < size:
            if pos + PACKET_HEADER > size:
                raise self._refuse(number, f"{size - pos} bytes at offset {pos}: a packet header takes "
                                           f"{PACKET_HEADER}; likely cause: the file was cut short")
            (length,), _ = self._header_fields(data, np.array([pos]))
            if not 0 < length <= MAX_PACKET or pos + PACKET_HEADER + length > size:
                raise self._refuse(number, f"packet at offset {pos} claims {length} payload bytes, "
                                           f"{size - pos - PACKET_HEADER} remain; likely cause: not a mmWave Studio "
                                           f"Raw file (an adc_data.bin?), or a file cut short")
            stride = PACKET_HEADER + length
            if length < MIN_PACKET and pos + stride < size:
                raise self._refuse(number, f"packet at offset {pos} carries {length} payload bytes, a DCA1000 packet "
                                           f"carries at least {MIN_PACKET} (1456 by default) unless it is a file's "
                                           f"last; likely cause: not a mmWave Studio Raw file")
            starts = pos + stride * np.arange(min(window, (size - pos) // stride))
            lengths, positions = self._header_fields(data, starts)
            same = int(np.argmin(lengths == length)) if (lengths != length).any() else starts.size
            rows[count:count + same] = np.column_stack([np.full(same, number), starts[:same] + PACKET_HEADER,
                                                        np.full(same, length), positions[:same]])
            pos, count = pos + same * stride, count + same
            if same < starts.size:
                changes += 1
                window = _FIRST_RUN
                if changes > MAX_LENGTH_CHANGES:
                    raise self._refuse(number, f"packet lengths change more than {MAX_LENGTH_CHANGES} times; a "
                                               f"DCA1000 stream's packets have one length; likely cause: not a "
                                               f"mmWave Studio Raw file")
            else:
                window = min(2 * window, _MAX_RUN)
        return rows[:count]

    def read(self, start: int, size: int) -> tuple[bytes, int]:
        """Stream bytes [start, start + size), zero where no packet carried them, and how many those are."""
        out = np.zeros(size, np.uint8)
        covered = 0
        t = self.table
        first = max(int(np.searchsorted(t[:, 3], start, side="right")) - 1, 0)
        for number, offset, length, position in t[first:]:
            if position >= start + size:
                break
            lo, hi = max(position, start), min(position + length, start + size)
            if hi > lo:
                out[lo - start:hi - start] = self.maps[number][offset + lo - position:offset + hi - position]
                covered += hi - lo
        return out.tobytes(), size - covered


def frames_from_bytes(data: bytes | memoryview, profile: RadarProfile, fmt: CaptureFormat | None = None, *,
                      source: str = "payload", partial: str = "refuse") -> np.ndarray:
    """The frames in ``data`` (a DCA1000 stream's bytes: a capture file's content or reassembled UDP payloads) as
    (frames, chirps, rx, samples) complex64, checked against ``profile`` like a capture file (one line when not)."""
    fmt = fmt or CaptureFormat.of_profile(profile)
    geometry = FrameGeometry.of_profile(profile, fmt)
    problem = geometry.layout_problem(fmt)
    if problem:
        raise DataError(source, f"{fmt.describe()}: {problem}")
    count = _check_size(Path(source), len(data), geometry, partial, "the data")
    words = np.frombuffer(data, dtype="<u2", count=count * geometry.words)
    n = geometry.words
    return np.stack([decode_frame(words[i * n:(i + 1) * n], fmt, geometry) for i in range(count)])
