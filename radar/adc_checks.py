"""Plausibility checks of raw ADC samples, run on every path that takes them (``process-adc``, ADC recordings,
``segment --input adc``, the service's ``?input=adc``, captures and the viewer), as complex and magnitude cubes get
theirs (radar.input_kind).

Each check names the likely mistake:

- **two's-complement words read as unsigned** (both parts whole numbers within 0..65535, and decoding them shrinks
  the spread many times: small negative samples became values near 65535): refused, "decode with
  ((x + 32768) % 65536) - 32768";
- **offset-binary words** (whole numbers within 0..65535 clustered around 32768): refused, "subtract 32768";
- **offset-binary words decoded as two's complement** (a capture read without ``--offset-binary``: whole numbers
  crowded at both ends of the ADC's full scale, and flipping their top bit shrinks the spread many times; the
  clipping check would call them clipped): refused, naming ``--offset-binary``;
- **a dominant DC** (a channel's mean over its samples larger than its spread about that mean): warned; refused
  when the mean is :data:`DC_REFUSE_RATIO` times the spread (nothing but an offset: every frame would show one
  range-0 peak and its window's leakage);
- **clipping** (a share of the parts at the 16-bit full scale, or piled up on the frame's own extreme value):
  warned with the share.

Refusals raise :class:`AdcCheckError` (a user error: one line, exit status 2, HTTP 422); warnings are logged on
``radar.adc_checks`` and returned.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from radar.errors import UserError

logger = logging.getLogger(__name__)

WORD_MAX = 65535  # the largest unsigned 16-bit word
WORD_HALF = 32768
SPREAD_SHRINK = 4.0  # decoding two's-complement words shrinks their spread at least this much
OFFSET_BINARY_SPREAD = 8192.0  # offset-binary words stay within this spread of 32768
DC_WARN_RATIO = 1.0  # a channel's |mean| over its spread about the mean: warned above this ...
DC_REFUSE_RATIO = 30.0  # ... refused above this
FULL_SCALE = 32767  # int16 full scale
CLIP_WARN_SHARE = 1e-3  # share of parts at full scale (or piled on the extreme) that is warned
PLATEAU_MIN_VALUE = 127  # a pile-up on the frame's extreme counts as clipping only above this magnitude
PLATEAU_MIN_COUNT = 8
FULL_SCALES = (2048, 8192, 32768)  # 12-, 14- and 16-bit ADCs: half their range
FAR_SHARE = 0.5  # offset-binary words decoded as two's complement: at least this share beyond half full scale


class AdcCheckError(UserError):
    """ADC samples that are not decoded signed samples: the message names the likely mistake and the fix."""


@dataclass(frozen=True)
class AdcFinding:
    """One check's verdict: ``refuse`` or warn, with the line a user reads."""

    check: str  # "twos_complement_words", "offset_binary_words", "offset_binary_decoded", "dc", "clipping"
    refuse: bool
    message: str


def _parts(adc: np.ndarray) -> np.ndarray:
    """The real and imaginary parts as float64 on a trailing axis of 2 (a real array gets a zero imaginary part)."""
    if np.iscomplexobj(adc):
        return np.stack([adc.real, adc.imag], axis=-1).astype(np.float64, copy=False)
    return np.stack([adc, np.zeros_like(adc)], axis=-1).astype(np.float64, copy=False)


def _word_findings(parts: np.ndarray) -> list[AdcFinding]:
    """Undecoded 16-bit words: whole numbers within 0..65535 in both parts."""
    low, high = float(parts.min()), float(parts.max())
    if low < 0 or high > WORD_MAX or high < 1 or not np.array_equal(parts, np.round(parts)):
        return []
    raw_spread = float(parts.std())
    decoded = np.where(parts >= WORD_HALF, parts - 2 * WORD_HALF, parts)
    if high >= WORD_HALF and float(decoded.std()) * SPREAD_SHRINK < raw_spread:
        return [AdcFinding("twos_complement_words", True,
                           f"ADC samples are whole numbers within {low:.0f}..{high:.0f} in both I and Q: they look "
                           f"like raw unsigned 16-bit words; decode with ((x + 32768) % 65536) - 32768")]
    if abs(float(parts.mean()) - WORD_HALF) < OFFSET_BINARY_SPREAD and raw_spread < OFFSET_BINARY_SPREAD:
        return [AdcFinding("offset_binary_words", True,
                           f"ADC samples are whole numbers within {low:.0f}..{high:.0f} centred on "
                           f"{float(parts.mean()):.0f}: they look like offset-binary 16-bit words; subtract 32768")]
    return []


def _offset_binary_finding(parts: np.ndarray) -> list[AdcFinding]:
    """Offset-binary words decoded as two's complement: a small sample s became s - full (s >= 0) or s + full (s < 0),
    so the parts crowd both ends of the full scale and flipping the top bit brings them back near zero."""
    largest = float(np.abs(parts).max())
    full = next((scale for scale in FULL_SCALES if largest <= scale), None)
    if full is None or largest < full / 2 or not np.array_equal(parts, np.round(parts)):
        return []
    far = float(np.mean(np.abs(parts) > full / 2))
    flipped = np.where(parts < 0, parts + full, parts - full)
    if far < FAR_SHARE or float(flipped.std()) * SPREAD_SHRINK >= float(parts.std()):
        return []
    low, high = float(np.mean(parts < -full / 2)), float(np.mean(parts > full / 2))
    return [AdcFinding("offset_binary_decoded", True,
                       f"{far:.1%} of the ADC samples' I and Q parts sit beyond +-{full // 2} ({low:.1%} near -{full}, "
                       f"{high:.1%} near +{full}), and flipping their top bit shrinks their spread "
                       f"{float(parts.std()) / max(float(flipped.std()), 1e-12):.3g}x: offset-binary words read as "
                       f"two's complement, not clipping; read the capture with --offset-binary (a profile's "
                       f"[capture] offset_binary = true)")]


def _dc_finding(adc: np.ndarray, channel_axis: int) -> list[AdcFinding]:
    """The worst channel's |mean| over its spread about the mean."""
    moved = np.moveaxis(adc, channel_axis, 0).reshape(adc.shape[channel_axis], -1)
    mean = moved.mean(axis=1)
    spread = np.sqrt(np.mean(np.abs(moved - mean[:, None]) ** 2, axis=1))
    ratio = np.abs(mean) / np.maximum(spread, np.finfo(np.float64).tiny)
    worst = int(np.argmax(ratio))
    if ratio[worst] <= DC_WARN_RATIO or np.abs(mean[worst]) == 0:
        return []
    refuse = bool(ratio[worst] > DC_REFUSE_RATIO)
    verdict = ("nothing but an offset" if refuse else "a DC offset dominates (every frame gets a range-0 peak and "
                                                      "its window's leakage)")
    return [AdcFinding("dc", refuse,
                       f"ADC channel {worst}: its mean {complex(mean[worst]):.4g} is {ratio[worst]:.3g}x its spread "
                       f"({spread[worst]:.4g}): {verdict}; undecoded offset-binary words, or an ADC without DC "
                       f"removal? subtract each channel's mean")]


def _clipping_finding(parts: np.ndarray) -> list[AdcFinding]:
    """Parts at the int16 full scale, or piled up on the frame's own largest magnitude."""
    magnitude = np.abs(parts)
    largest = float(magnitude.max())
    at_full_scale = int(np.count_nonzero(magnitude >= FULL_SCALE))
    at_extreme = int(np.count_nonzero(magnitude == largest)) if largest >= PLATEAU_MIN_VALUE else 0
    clipped, level = (at_full_scale, FULL_SCALE) if at_full_scale else (at_extreme, largest)
    share = clipped / magnitude.size
    if clipped < PLATEAU_MIN_COUNT or share <= CLIP_WARN_SHARE:
        return []
    return [AdcFinding("clipping", False,
                       f"{share:.2%} of the ADC samples' I and Q parts sit at +-{level:.6g}: the ADC clipped (RX gain "
                       f"too high, or a reflector too close); strong targets get harmonics and smeared peaks")]


def adc_findings(adc: np.ndarray, *, channel_axis: int = -1) -> list[AdcFinding]:
    """Every check's finding on one frame of finite ADC samples (``channel_axis``: the receive channel or
    virtual element axis); empty when the samples look like decoded signed samples."""
    parts = _parts(adc)
    words = _word_findings(parts) or _offset_binary_finding(parts)
    if words:
        return words
    return _dc_finding(adc, channel_axis) + _clipping_finding(parts)


def check_adc(adc: np.ndarray, *, channel_axis: int = -1, source: str | None = None) -> list[str]:
    """Refuse (AdcCheckError, naming ``source``) the first finding that refuses; log and return the warnings."""
    findings = adc_findings(adc, channel_axis=channel_axis)
    prefix = f"{source}: " if source else ""
    for finding in findings:
        if finding.refuse:
            raise AdcCheckError(prefix + finding.message)
    for finding in findings:
        logger.warning("%s%s", prefix, finding.message)
    return [prefix + finding.message for finding in findings]
