"""ADC recordings whose samples are DCA1000 captures: ``seq_NNN/adc_data.bin`` per sequence instead of one ``.npy``
per frame (``radarseg simulate --adc --format dca1000``; a real capture can be dropped in the same way).

``recording.json`` then says ``"adc_format": "dca1000"``, the ``capture`` settings (radar/ti/dca1000.py's
CaptureFormat) and ``adc_scale``: the words are ``round(samples x adc_scale)``; read back, they are divided by it, so
that a simulated recording's cubes keep the simulator's levels (noise floor, SNR calibration). The simulator's samples
are scaled so that the thermal noise is :data:`NOISE_WORDS` words (complex rms), a real radar's level, far from
clipping; clipped samples are counted in ``recording.json``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from radar.adc import chain_constants, sck_to_ti
from radar.errors import DataError
from radar.profiles import RadarProfile
from radar.ti.capture import Capture
from radar.ti.capture_writer import quantize
from radar.ti.dca1000 import CaptureFormat, encode_frame

CAPTURE_FILE = "adc_data.bin"
NOISE_WORDS = 16.0


class CaptureAppender:
    """Appends each sequence's simulated frames (sck layout) to its ``adc_data.bin``."""

    def __init__(self, profile: RadarProfile):
        self.profile = profile
        self.format = CaptureFormat.of_profile(profile)
        self.scale = NOISE_WORDS / chain_constants(profile).adc_noise_std
        self.clipped = 0

    def append(self, seq_dir: Path, adc_sck: np.ndarray, index: int) -> None:
        words, clipped = quantize(sck_to_ti(adc_sck, self.profile), self.scale, self.format)
        self.clipped += clipped
        with (seq_dir / CAPTURE_FILE).open("wb" if index == 0 else "ab") as fh:
            fh.write(encode_frame(words, self.format).astype("<u2").tobytes())

    def meta(self) -> dict[str, Any]:
        return {"adc_format": "dca1000", "capture": dataclasses.asdict(self.format), "adc_scale": self.scale,
                "clipped_samples": self.clipped}


class RecordedCaptures:
    """The per-sequence captures of a recording, opened on first use; frames in the ``"ti"`` layout, unscaled."""

    def __init__(self, root: Path, profile: RadarProfile, meta: dict[str, Any], meta_path: Path):
        try:
            self.format = CaptureFormat(**meta["capture"])
            self.scale = float(meta["adc_scale"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(meta_path, f"a DCA1000 ADC recording needs 'capture' settings and 'adc_scale' ({exc})"
                            ) from None
        if not np.isfinite(self.scale) or self.scale <= 0:
            raise DataError(meta_path, f"adc_scale must be a positive number, got {self.scale}")
        self.root, self.profile = root, profile
        self._open: dict[str, Capture] = {}

    def frame(self, sequence: str, index: int) -> np.ndarray:
        if sequence not in self._open:
            self._open[sequence] = Capture(self.root / sequence / CAPTURE_FILE, self.profile, self.format)
        return self._open[sequence].frame(index) / np.float32(self.scale)
