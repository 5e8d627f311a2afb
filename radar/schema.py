"""Cube schema: a small machine-readable description of what a RAD cube's numbers mean.

Stored with recordings (recording.json), in store attributes and in checkpoints, and checked wherever a
cube meets a model: a mismatch is refused with a message naming each difference (not just a shape).

    {"format": "radarseg.cube-schema", "version": 1, "profile": "carrada", "fingerprint": "0f82...",
     "shape": [256, 256, 64], "axes": ["range", "angle", "doppler"], "content": "complex",
     "range":   {"unit": "m", "first": 0.0, "step": 0.1953125, "orientation": "bin 0 nearest"},
     "angle":   {"unit": "sin(azimuth)", "first": -1.0, "step": 0.0078125, "orientation": "positive right"},
     "doppler": {"unit": "m/s", "first": -13.43, "step": 0.41968, "orientation": "positive receding"},
     "window": "hann"}

``content`` is ``complex`` (complex64 I/Q after the FFT chain), ``magnitude`` or ``log_power_db``
(``10 log10(|I|^2 + 1)``).
"""

from __future__ import annotations

import math
from typing import Any

from radar.profiles import RadarProfile

FORMAT = "radarseg.cube-schema"
VERSION = 1
CONTENTS = ("complex", "magnitude", "log_power_db")


class SchemaMismatch(ValueError):
    """A cube described by one schema offered where another is expected."""


def cube_schema(profile: RadarProfile, content: str = "complex") -> dict[str, Any]:
    """The schema of ``profile``'s cubes holding ``content``."""
    if content not in CONTENTS:
        raise ValueError(f"content must be one of {CONTENTS}, got {content!r}")
    return {
        "format": FORMAT, "version": VERSION, "profile": profile.name, "fingerprint": profile.fingerprint,
        "shape": list(profile.shape), "axes": ["range", "angle", "doppler"], "content": content,
        "range": {"unit": "m", "first": 0.0, "step": profile.range_res, "orientation": "bin 0 nearest"},
        "angle": {"unit": "sin(azimuth)", "first": -1.0, "step": 2.0 / profile.n_angle,
                  "orientation": "positive right"},
        "doppler": {"unit": "m/s", "first": float(profile.velocity_mps(0)), "step": profile.velocity_res,
                    "orientation": "positive receding"},
        "window": profile.window,
    }


def _close(a: Any, b: Any) -> bool:
    if isinstance(a, float | int) and isinstance(b, float | int) and not isinstance(a, bool):
        return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)
    return a == b


def schema_differences(expected: dict[str, Any], given: dict[str, Any]) -> list[str]:
    """Human-readable differences, e.g. ``range.step: expected 0.1953 m, got 0.3906 m``; empty if equal.
    The content kind and the profile fingerprint are compared too (the fingerprint last: it only adds
    information when every listed field agrees)."""
    if not isinstance(given, dict) or given.get("format") != FORMAT:
        return [f"not a {FORMAT} description"]
    diffs = []
    for key in ("shape", "axes", "content", "window"):
        if not _close(expected.get(key), given.get(key)):
            diffs.append(f"{key}: expected {expected.get(key)!r}, got {given.get(key)!r}")
    for axis in ("range", "angle", "doppler"):
        exp, got = expected.get(axis, {}), given.get(axis) or {}
        for field in ("unit", "first", "step", "orientation"):
            if not _close(exp.get(field), got.get(field)):
                unit = exp.get("unit", "") if field in ("first", "step") else ""
                diffs.append(f"{axis}.{field}: expected {exp.get(field)!r} {unit}".rstrip()
                             + f", got {got.get(field)!r}")
    if not diffs and expected.get("fingerprint") != given.get("fingerprint"):
        diffs.append(f"profile fingerprint: expected {expected.get('fingerprint')} ({expected.get('profile')}), got "
                     f"{given.get('fingerprint')} ({given.get('profile')}): same bins, different chirp or array")
    return diffs


def check_schema(expected: dict[str, Any], given: dict[str, Any], *, what: str = "cube") -> None:
    """Raise :class:`SchemaMismatch` naming every difference between two schemas."""
    diffs = schema_differences(expected, given)
    if diffs:
        raise SchemaMismatch(f"{what} does not match the expected schema ({expected.get('profile')}): "
                             + "; ".join(diffs))
