"""What an input cube holds, and the one rule for accepting it (docs/design.md section 2).

Used by ``radarseg segment`` (``--input``) and by the service (``?input=``), so both take the same kinds
with the same dtypes and refuse the same mistakes:

- ``complex``: the complex RAD cube ``(R, A, D)`` (complex64/complex128);
- ``magnitude``: its linear magnitude ``|I|`` (float16/32/64, never negative);
- ``log_power``: its log power ``10 log10(|I|^2 + 1)`` in dB (float16/32/64);
- ``adc``: raw complex ADC samples ``(samples, chirps, virtual elements)``, processed by :mod:`radar.adc`.

A complex dtype is a complex cube unless ``adc`` is declared; a real-valued cube must be declared (guessing
turned log power into "no objects" and linear magnitude into a screen of "cars" at score 1.0).
:func:`check_values` refuses values impossible for the declared kind and names the likely mistake:

- log power is never negative (``+ 1`` inside the logarithm) and never above :data:`MAX_LOG_POWER_DB`; its
  maximum lies less than :data:`MAX_DYNAMIC_RANGE_DB` above its median (the noise floor): linear values
  declared as dB break one of these (a magnitude of 1e6 is "1e6 dB");
- a magnitude is never negative; dB values declared as a magnitude have a small top-to-median ratio
  (a real cube's objects and clutter stand 20 dB and more above its noise: ratio >= 10) and small values.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from radar.adc_checks import adc_findings


class InputKind(StrEnum):
    """What a cube holds."""

    complex = "complex"  # complex RAD cube (complex64 or complex128)
    magnitude = "magnitude"  # |I|, linear (float16/32/64)
    log_power = "log_power"  # 10 log10(|I|^2 + 1) in dB (float16/32/64)
    adc = "adc"  # raw complex ADC samples (samples, chirps, virtual elements), processed by radar.adc


COMPLEX_DTYPES = (np.complex64, np.complex128)
REAL_DTYPES = (np.float16, np.float32, np.float64)
ACCEPTED_DTYPES: dict[InputKind, tuple[type, ...]] = {
    InputKind.complex: COMPLEX_DTYPES, InputKind.magnitude: REAL_DTYPES,
    InputKind.log_power: REAL_DTYPES, InputKind.adc: COMPLEX_DTYPES,
}
# radar.schema's ``content`` of each kind of RAD cube (ADC is processed into a complex cube first)
SCHEMA_CONTENT = {InputKind.complex: "complex", InputKind.magnitude: "magnitude",
                  InputKind.log_power: "log_power_db", InputKind.adc: "complex"}

MAX_LOG_POWER_DB = 300.0  # |I| = 1e15; our cubes peak near 120 dB
MAX_DYNAMIC_RANGE_DB = 150.0  # max - median of log power; ours about 65 dB
MIN_LOG_POWER_DB = -0.5  # 10 log10(|I|^2 + 1) >= 0; a little slack for float16 rounding
DB_LIKE_MAX = 200.0  # a "magnitude" whose values all stay below this ...
DB_LIKE_RATIO = 10.0  # ... and whose max is under 10x its median looks like dB
_SAMPLE = 65_537  # values drawn (evenly) for the median: the test stays a few ms on a 64 MiB cube


class InputKindError(ValueError):
    """A cube whose dtype or values do not fit the declared input kind; the message names the likely mistake."""


def kind_names() -> str:
    return ", ".join(kind.value for kind in InputKind)


def parse_kind(name: str) -> InputKind:
    """An InputKind by name; InputKindError naming the kinds for any other."""
    try:
        return InputKind(name)
    except ValueError:
        raise InputKindError(f"unknown input kind {name!r}: expected one of {kind_names()}") from None


def resolve_kind(dtype: np.dtype, declared: InputKind | str | None, *, flag: str = "--input {}") -> InputKind:
    """The kind of a cube of ``dtype``: the declared one if the dtype fits it; a complex dtype defaults to
    ``complex``; a real dtype must be declared (``flag``, a format string such as ``"--input {}"``, names how)."""
    dtype = np.dtype(dtype)
    kind = parse_kind(declared) if isinstance(declared, str) else declared
    if kind is None:
        if np.issubdtype(dtype, np.complexfloating):
            return InputKind.complex
        raise InputKindError(f"a real-valued {dtype.name} cube: say what it holds with {flag.format('magnitude')} or "
                             f"{flag.format('log_power')} (kinds: {kind_names()})")
    if dtype.newbyteorder("=") not in [np.dtype(d) for d in ACCEPTED_DTYPES[kind]]:
        names = "/".join(np.dtype(d).name for d in ACCEPTED_DTYPES[kind])
        hint = (f"; a real-valued cube is {flag.format('magnitude')} or {flag.format('log_power')}"
                if np.issubdtype(dtype, np.floating) else
                f"; a complex cube is {flag.format('complex')}" if np.issubdtype(dtype, np.complexfloating) else "")
        raise InputKindError(f"dtype {dtype.name} does not fit {flag.format(kind.value)} (expects {names}){hint}")
    return kind


def _median(values: np.ndarray) -> float:
    flat = values.reshape(-1)
    step = max(1, flat.size // _SAMPLE)
    return float(np.median(flat[::step].astype(np.float64)))


def check_values(cube: np.ndarray, kind: InputKind, *, flag: str = "--input {}") -> None:
    """InputKindError when the values of ``cube`` are impossible for ``kind`` (see the module docstring);
    complex cubes take any finite value, ADC samples what radar.adc_checks does not refuse (undecoded words)."""
    if kind is InputKind.adc:
        refused = [f for f in adc_findings(cube, channel_axis=2) if f.refuse]  # (samples, chirps, virtual elements)
        if refused:
            raise InputKindError(f"{refused[0].message} ({flag.format('adc')} takes decoded signed samples)")
    elif kind is InputKind.log_power:
        low, high, median = float(cube.min()), float(cube.max()), _median(cube)
        if low < MIN_LOG_POWER_DB:
            raise InputKindError(
                f"log power down to {low:.4g} dB, but 10 log10(|I|^2 + 1) is never negative: normalised or "
                f"20 log10|I| values? ({flag.format('log_power')} takes 10 log10(|I|^2 + 1) in dB)")
        if high > MAX_LOG_POWER_DB or high - median > MAX_DYNAMIC_RANGE_DB:
            raise InputKindError(
                f"log power up to {high:.4g} dB over a median of {median:.4g} dB is not plausible (at most "
                f"{MAX_LOG_POWER_DB:g} dB, {MAX_DYNAMIC_RANGE_DB:g} dB above the median): linear magnitude or power? "
                f"send it as {flag.format('magnitude')}, or its log power in dB")
    elif kind is InputKind.magnitude:
        low, high, median = float(cube.min()), float(cube.max()), _median(cube)
        if low < 0:
            raise InputKindError(f"magnitude down to {low:.4g}, but |I| is never negative: the real part of a "
                                 f"complex cube, or normalised log power? ({flag.format('complex')}, "
                                 f"{flag.format('log_power')})")
        if high <= DB_LIKE_MAX and median > 0 and high < DB_LIKE_RATIO * median:
            raise InputKindError(
                f"magnitude between {low:.4g} and {high:.4g} with median {median:.4g} looks like log power in dB "
                f"(a magnitude cube's peaks stand 10x and more above its median): send it as "
                f"{flag.format('log_power')}")
