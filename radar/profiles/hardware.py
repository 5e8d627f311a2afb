"""The profile file's keys for a real radar's hardware (what ``radarseg radar from-ti`` writes; radar/profiles/files.py
reads them through these functions):

- ``[chirp]`` TI's timing as TI states it: ``idle_time_s``, ``adc_start_time_s``, ``ramp_end_time_s``,
  ``tx_start_time_s``; ``adc = "complex" | "real"``. With idle and ramp end stated, ``chirp_cycle_s`` may be left out:
  a TDM cycle fires every TX once, ``n_tx x (idle + ramp end)``. The ADC window must end before the ramp does.
- ``[array]`` ``virtual_azimuth`` and ``virtual_elevation``: each virtual element's position (element
  ``k = tx * n_rx + rx``) in half wavelengths.
- ``[calibration]`` ``range_bias_m`` and ``channel_coefficients``: one ``[re, im]`` per virtual element, multiplied
  into that element's samples (TI's ``compRangeBiasAndRxChanPhase``).
- ``[capture]`` how a capture card stores the ADC words: ``format = "dca1000"``, ``lvds_lanes`` (2 or 4),
  ``iq_order`` ("iq": I first, "qi"), ``offset_binary`` (words stored as unsigned with 0 at 32768), ``adc_bits``
  (16, 14 or 12: narrower words are sign-extended from that many bits).

Every function raises ValueError with the reason; the file loader adds the file's name.
"""

from __future__ import annotations

import math
from typing import Any

from radar.profiles.profile import ChannelCalibration, RadarProfile

TIMING_KEYS = ("idle_time_s", "adc_start_time_s", "ramp_end_time_s", "tx_start_time_s")
CHIRP_KEYS = (*TIMING_KEYS, "adc")
ARRAY_KEYS = ("virtual_azimuth", "virtual_elevation")
CALIBRATION_KEYS = ("range_bias_m", "channel_coefficients")
CAPTURE_KEYS = ("format", "lvds_lanes", "iq_order", "offset_binary", "adc_bits")
CAPTURE_DEFAULTS: dict[str, Any] = {"format": "dca1000", "lvds_lanes": 2, "iq_order": "iq", "offset_binary": False,
                                    "adc_bits": 16}
CAPTURE_CHOICES: dict[str, tuple] = {"format": ("dca1000",), "lvds_lanes": (2, 4), "iq_order": ("iq", "qi"),
                                     "offset_binary": (False, True), "adc_bits": (16, 14, 12)}
CYCLE_TOLERANCE = 0.005  # relative: a stated chirp_cycle_s against the one TI's timing gives


def _finite(value: Any, key: str, *, minimum: float = 0.0) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < minimum:
        raise ValueError(f"{key} must be a finite number >= {minimum:g}, got {value!r}")
    return float(value)


def chirp_timing(chirp: dict, n_tx: int, adc_time_s: float, stated_cycle_s: float | None
                 ) -> tuple[float, dict[str, Any]]:
    """(chirp cycle in s, ChirpParameters keyword arguments) from ``[chirp]``'s timing keys."""
    timing = {key: _finite(chirp[key], key) for key in TIMING_KEYS if key in chirp}
    adc = chirp.get("adc", "complex")
    if adc not in ("complex", "real"):
        raise ValueError(f"[chirp] adc must be 'complex' or 'real', got {adc!r}")
    idle, ramp_end = timing.get("idle_time_s"), timing.get("ramp_end_time_s")
    if ramp_end is not None and timing.get("adc_start_time_s", 0.0) + adc_time_s > ramp_end * (1 + 1e-9):
        raise ValueError(f"the ADC window ({timing.get('adc_start_time_s', 0.0) * 1e6:.4g} us start + "
                         f"{adc_time_s * 1e6:.4g} us sampling) ends after the ramp ({ramp_end * 1e6:.4g} us)")
    cycle = stated_cycle_s
    if idle is not None and ramp_end is not None:
        tdm_cycle = n_tx * (idle + ramp_end)
        if cycle is not None and abs(cycle / tdm_cycle - 1) > CYCLE_TOLERANCE:
            raise ValueError(f"chirp_cycle_s {cycle * 1e6:.4g} us, but {n_tx} TX x (idle {idle * 1e6:.4g} + ramp end "
                             f"{ramp_end * 1e6:.4g} us) = {tdm_cycle * 1e6:.4g} us")
        cycle = tdm_cycle if cycle is None else cycle
    if cycle is None:
        raise ValueError("[chirp] needs chirp_cycle_s, or idle_time_s and ramp_end_time_s")
    return cycle, {**timing, "real_adc": adc == "real"}


def antenna_positions(array: dict, n_virtual: int) -> tuple[tuple[float, float], ...]:
    """``[array]``'s virtual_azimuth and virtual_elevation as (azimuth, elevation) pairs; () when not stated."""
    if not any(key in array for key in ARRAY_KEYS):
        return ()
    rows = []
    for key in ARRAY_KEYS:
        row = array.get(key, [0.0] * n_virtual)
        if not isinstance(row, list) or len(row) != n_virtual:
            raise ValueError(f"[array] {key} must list one position per virtual element ({n_virtual}), got {row!r}")
        rows.append([_finite(v, key, minimum=-1e3) for v in row])
    return tuple(zip(rows[0], rows[1], strict=True))


def calibration(table: dict, n_virtual: int) -> ChannelCalibration | None:
    """``[calibration]`` as a :class:`ChannelCalibration`; None when the table is absent or empty."""
    if not table:
        return None
    bias = _finite(table.get("range_bias_m", 0.0), "range_bias_m", minimum=-1e3)
    pairs = table.get("channel_coefficients", [[1.0, 0.0]] * n_virtual)
    if not (isinstance(pairs, list) and len(pairs) == n_virtual
            and all(isinstance(p, list) and len(p) == 2 for p in pairs)):
        raise ValueError(f"[calibration] channel_coefficients must be one [re, im] per virtual element ({n_virtual})")
    coefficients = tuple(complex(_finite(re, "re", minimum=-1e6), _finite(im, "im", minimum=-1e6)) for re, im in pairs)
    if any(c == 0 for c in coefficients):
        raise ValueError("[calibration] channel_coefficients must not be 0 (that would erase a channel)")
    return ChannelCalibration(bias, coefficients)


def capture(table: dict) -> tuple[tuple[str, Any], ...]:
    """``[capture]`` as sorted (key, value) pairs with the defaults filled in; () when the table is absent."""
    if not table:
        return ()
    options = {**CAPTURE_DEFAULTS, **table}
    for key, choices in CAPTURE_CHOICES.items():
        value = options[key]
        if type(value) is not type(choices[0]) or value not in choices:
            raise ValueError(f"[capture] {key} must be one of {list(choices)}, got {value!r}")
    return tuple(sorted(options.items()))


def hardware_tables(profile: RadarProfile) -> dict[str, Any]:
    """The keys above of ``profile`` in file form, table by table, for merging into ``profile_to_dict``'s output."""
    chirp = profile.chirp
    out: dict[str, Any] = {"chirp": {}, "array": {}}
    if chirp is not None:
        out["chirp"] = {key: getattr(chirp, key) for key in TIMING_KEYS if getattr(chirp, key) is not None}
        if chirp.real_adc:
            out["chirp"]["adc"] = "real"
    if profile.antenna_positions:
        out["array"] = {"virtual_azimuth": [p[0] for p in profile.antenna_positions],
                        "virtual_elevation": [p[1] for p in profile.antenna_positions]}
    if profile.calibration is not None:
        out["calibration"] = {"range_bias_m": profile.calibration.range_bias_m,
                              "channel_coefficients": [[c.real, c.imag] for c in profile.calibration.coefficients]}
    if profile.capture:
        out["capture"] = dict(profile.capture)
    return out


def describe_rows(profile: RadarProfile) -> list[tuple[str, str]]:
    """``radarseg radar show``'s rows for the keys above (none when the profile states none of them)."""
    rows = []
    chirp = profile.chirp
    if chirp is not None and chirp.ramp_end_time_s is not None:
        rows.append(("TI timing", ", ".join(f"{key[:-7].replace('_', ' ')} {getattr(chirp, key) * 1e6:.4g} us"
                                            for key in TIMING_KEYS if getattr(chirp, key) is not None)))
    if chirp is not None and chirp.real_adc:
        rows.append(("ADC", f"real (I only): range bins past {profile.n_range // 2} mirror the first half; usable "
                            f"range {profile.max_range / 2:.2f} m"))
    if profile.antenna_positions:
        rows.append(("virtual azimuth (lambda/2)", " ".join(f"{p[0]:g}" for p in profile.antenna_positions)))
        rows.append(("virtual elevation (lambda/2)", " ".join(f"{p[1]:g}" for p in profile.antenna_positions)))
    if profile.calibration is not None:
        cal = profile.calibration
        rows.append(("calibration", f"range bias {cal.range_bias_m:.4f} m (not applied to the bins); channel gain "
                                    + " ".join(f"{abs(c):.3f}/{math.degrees(math.atan2(c.imag, c.real)):+.1f}deg"
                                               for c in cal.coefficients)))
    if profile.capture:
        rows.append(("capture", ", ".join(f"{k} {v}" for k, v in profile.capture)))
    return rows
