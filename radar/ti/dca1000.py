"""The DCA1000's ADC words: how one frame's samples sit in a capture (``adc_data.bin``), decoded into the ADC chain's
``"ti"`` layout (chirps, rx, samples) complex64 and encoded back.

Byte order, as TI's capture scripts (readDCA1000.m for xWR12xx/14xx, xWR16xx) and OpenRadar's
``mmwave.dataloader.DCA1000.organize`` read it: 16-bit little-endian words; frames one after another, chirps in firing
order within a frame.

- 2 LVDS lanes (xWR16xx, xWR18xx, xWR68xx; non-interleaved): per chirp, RX by RX, the samples; complex samples come in
  groups of four words ``I(n) I(n+1) Q(n) Q(n+1)``; real samples one word each.
- 4 LVDS lanes (xWR12xx, xWR14xx; one lane per RX, all four RX): per chirp, sample by sample, the four RX; complex:
  ``I(rx0..rx3)`` then ``Q(rx0..rx3)``; real: one word per RX.

Options: ``iq_order = "qi"`` swaps the two halves of every complex group; ``offset_binary`` words are unsigned with 0 at
2^(bits-1); ``adc_bits`` 12 or 14: the low bits hold a two's-complement sample (sign-extended here). Real-only ADC
comes back with a zero imaginary part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar.profiles import RadarProfile

LANES = (2, 4)


@dataclass(frozen=True)
class CaptureFormat:
    """How a capture stores the ADC words (a profile's ``[capture]`` table, or command-line options)."""

    lvds_lanes: int = 2
    complex_adc: bool = True
    iq_order: str = "iq"  # "iq": I first; "qi": Q first
    offset_binary: bool = False
    adc_bits: int = 16

    def __post_init__(self) -> None:
        if self.lvds_lanes not in LANES:
            raise ValueError(f"lvds_lanes must be one of {list(LANES)}, got {self.lvds_lanes!r}")
        if self.iq_order not in ("iq", "qi"):
            raise ValueError(f"iq_order must be 'iq' or 'qi', got {self.iq_order!r}")
        if self.adc_bits not in (12, 14, 16):
            raise ValueError(f"adc_bits must be 12, 14 or 16, got {self.adc_bits!r}")

    @classmethod
    def of_profile(cls, profile: RadarProfile, **overrides) -> CaptureFormat:
        """The profile's ``[capture]`` (defaults where it states none; real or complex from its ``[chirp]`` adc), with
        ``overrides`` (None values ignored) on top."""
        stated = dict(profile.capture)
        options = {"lvds_lanes": stated.get("lvds_lanes", 2), "iq_order": stated.get("iq_order", "iq"),
                   "offset_binary": stated.get("offset_binary", False), "adc_bits": stated.get("adc_bits", 16),
                   "complex_adc": not (profile.chirp is not None and profile.chirp.real_adc)}
        options.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**options)

    def describe(self) -> str:
        return (f"{'complex' if self.complex_adc else 'real'} {self.adc_bits}-bit, {self.lvds_lanes} LVDS lanes"
                + (f", {self.iq_order.upper()} order" if self.complex_adc else "")
                + (", offset binary" if self.offset_binary else ""))


@dataclass(frozen=True)
class FrameGeometry:
    """One frame's samples: all chirps of a frame (cycles x TX), RX channels, samples per chirp."""

    chirps: int
    rx: int
    samples: int
    complex_adc: bool = True

    @classmethod
    def of_profile(cls, profile: RadarProfile, fmt: CaptureFormat) -> FrameGeometry:
        return cls(profile.n_chirps * profile.n_tx, profile.n_rx, profile.n_samples, fmt.complex_adc)

    @property
    def words(self) -> int:
        return self.chirps * self.rx * self.samples * (2 if self.complex_adc else 1)

    @property
    def bytes(self) -> int:
        return 2 * self.words

    def layout_problem(self, fmt: CaptureFormat) -> str | None:
        """Why ``fmt`` cannot hold frames of this geometry, or None."""
        if fmt.lvds_lanes == 4 and self.rx != 4:
            return f"4 LVDS lanes carry one RX each and need all 4 RX enabled; this radar has {self.rx} RX"
        if fmt.lvds_lanes == 2 and fmt.complex_adc and self.samples % 2:
            return f"2 LVDS lanes pair samples (I(n) I(n+1) Q(n) Q(n+1)); {self.samples} samples per chirp is odd"
        return None


def _to_signed(words: np.ndarray, fmt: CaptureFormat) -> np.ndarray:
    """uint16 words -> int32 sample values."""
    values = words.astype(np.int32)
    if fmt.adc_bits < 16:
        values &= (1 << fmt.adc_bits) - 1
    half = 1 << (fmt.adc_bits - 1)
    if fmt.offset_binary:
        return values - half
    return np.where(values >= half, values - 2 * half, values)


def _to_words(values: np.ndarray, fmt: CaptureFormat) -> np.ndarray:
    """int sample values -> uint16 words (inverse of :func:`_to_signed`)."""
    half = 1 << (fmt.adc_bits - 1)
    words = values + half if fmt.offset_binary else np.where(values < 0, values + 2 * half, values)
    return words.astype(np.uint16)


def decode_frame(words: np.ndarray, fmt: CaptureFormat, geometry: FrameGeometry) -> np.ndarray:
    """One frame's ``geometry.words`` uint16 words -> (chirps, rx, samples) complex64."""
    g = geometry
    values = _to_signed(np.asarray(words).reshape(-1), fmt).astype(np.float32)
    if values.size != g.words:
        raise ValueError(f"a frame holds {g.words} words, got {values.size}")
    if not fmt.complex_adc:
        if fmt.lvds_lanes == 2:
            real = values.reshape(g.chirps, g.rx, g.samples)
        else:
            real = values.reshape(g.chirps, g.samples, g.rx).transpose(0, 2, 1)
        return real.astype(np.complex64)
    if fmt.lvds_lanes == 2:
        groups = values.reshape(-1, 2, 2)  # (pair of samples, first/second half, sample n / n+1)
        first, second = groups[:, 0, :], groups[:, 1, :]
    else:
        groups = values.reshape(g.chirps, g.samples, 2, g.rx)  # (chirp, sample, half, rx)
        first, second = groups[:, :, 0, :], groups[:, :, 1, :]
    i, q = (first, second) if fmt.iq_order == "iq" else (second, first)
    samples = (i + 1j * q).astype(np.complex64)
    if fmt.lvds_lanes == 2:
        return samples.reshape(g.chirps, g.rx, g.samples)
    return np.ascontiguousarray(samples.transpose(0, 2, 1))


def encode_frame(frame: np.ndarray, fmt: CaptureFormat) -> np.ndarray:
    """(chirps, rx, samples) samples with whole-number parts -> the frame's uint16 words (inverse of
    :func:`decode_frame`). ValueError when a part is not a whole number the format can hold."""
    frame = np.asarray(frame)
    lo, hi = (0, (1 << fmt.adc_bits) - 1) if fmt.offset_binary else (-(1 << (fmt.adc_bits - 1)),
                                                                      (1 << (fmt.adc_bits - 1)) - 1)
    parts = [frame.real] + ([frame.imag] if fmt.complex_adc else [])
    if not fmt.complex_adc and np.iscomplexobj(frame) and np.any(frame.imag != 0):
        raise ValueError("a real-only capture cannot hold samples with an imaginary part")
    shift = (1 << (fmt.adc_bits - 1)) if fmt.offset_binary else 0
    for part in parts:
        if np.any(part != np.rint(part)) or part.min(initial=0) + shift < lo or part.max(initial=0) + shift > hi:
            raise ValueError(f"samples must be whole numbers within the {fmt.adc_bits}-bit range to be written")
    chirps, rx, samples = frame.shape
    real = frame.real.astype(np.int32)
    if not fmt.complex_adc:
        values = real if fmt.lvds_lanes == 2 else real.transpose(0, 2, 1)
        return _to_words(np.ascontiguousarray(values).reshape(-1), fmt)
    imag = frame.imag.astype(np.int32)
    first, second = (real, imag) if fmt.iq_order == "iq" else (imag, real)
    if fmt.lvds_lanes == 2:
        pairs = np.stack([first.reshape(-1, 2), second.reshape(-1, 2)], axis=1)  # (pair, half, n / n+1)
    else:
        pairs = np.stack([first.transpose(0, 2, 1), second.transpose(0, 2, 1)], axis=2)  # (chirp, sample, half, rx)
    return _to_words(pairs.reshape(-1), fmt)
