"""Writers of the capture formats radar/ti/capture.py reads (for tests, the simulator and replay): a DCA1000
``adc_data.bin`` and mmWave Studio's packet files ``PREFIX_Raw_N.bin``.

Samples must already be whole numbers in the ADC's range (:func:`quantize` scales simulated samples into it).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from radar.ti.dca1000 import CaptureFormat, encode_frame

PACKET_PAYLOAD = 1456  # bytes of ADC data per DCA1000 packet (the DCA1000's default, as OpenRadar uses)
MAX_FILE_BYTES = 1 << 30  # mmWave Studio / the DCA1000 CLI start a new Raw file at 1 GB


def quantize(samples: np.ndarray, scale: float, fmt: CaptureFormat) -> tuple[np.ndarray, int]:
    """``samples * scale`` rounded to whole numbers and clipped to the format's range; (values, clipped count)."""
    top = (1 << (fmt.adc_bits - 1)) - 1
    parts = [np.rint(samples.real * scale), np.rint(samples.imag * scale) if fmt.complex_adc else 0]
    clipped = sum(int(np.count_nonzero(np.abs(p) > top)) for p in parts if isinstance(p, np.ndarray))
    real, imag = (np.clip(p, -top - 1, top) if isinstance(p, np.ndarray) else p for p in parts)
    return (real + 1j * imag).astype(np.complex64), clipped


def write_dca1000(path: str | Path, frames: Iterable[np.ndarray], fmt: CaptureFormat) -> int:
    """Write (chirps, rx, samples) frames back to back as ``adc_data.bin``; the number of frames written."""
    count = 0
    with Path(path).open("wb") as fh:
        for frame in frames:
            fh.write(encode_frame(frame, fmt).astype("<u2").tobytes())
            count += 1
    return count


def _packets(stream: bytes, payload: int) -> Iterable[bytes]:
    for number, start in enumerate(range(0, len(stream), payload), start=1):
        chunk = stream[start:start + payload]
        yield (number.to_bytes(4, "little") + len(chunk).to_bytes(4, "little") + start.to_bytes(6, "little")
               + chunk)


def write_studio_raw(prefix: str | Path, frames: Iterable[np.ndarray], fmt: CaptureFormat, *,
                     payload: int = PACKET_PAYLOAD, max_file_bytes: int = MAX_FILE_BYTES,
                     drop: frozenset[int] = frozenset()) -> list[Path]:
    """Write frames as mmWave Studio's packet files ``PREFIX_Raw_0.bin``, ... (whole packets, a new file when the next
    would pass ``max_file_bytes``); packet numbers (from 1) in ``drop`` are left out, as lost. The files written."""
    stream = b"".join(encode_frame(frame, fmt).astype("<u2").tobytes() for frame in frames)
    prefix = Path(prefix)
    files: list[Path] = []
    fh, written = None, 0
    try:
        for number, packet in enumerate(_packets(stream, payload), start=1):
            if fh is None or written + len(packet) > max_file_bytes:
                if fh is not None:
                    fh.close()
                files.append(prefix.with_name(f"{prefix.name}_Raw_{len(files)}.bin"))
                fh, written = files[-1].open("wb"), 0
            if number not in drop:
                fh.write(packet)
                written += len(packet)
    finally:
        if fh is not None:
            fh.close()
    return files
