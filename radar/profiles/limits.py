"""Bounds on what a radar profile may describe, checked before anything the size of its cube is allocated.

A profile is operator input, but every command and the service build arrays from it (the cube, the ADC frame, the
angle FFT's steering tables, the simulator's objects, the tracker's tracks), so each value is checked against a
bound here, in one place, with one line naming the key, the value and the bound:

- the file itself (:func:`check_text`): its size and the nesting of its arrays and tables (a TOML array nested
  100,000 deep is a RecursionError in the parser otherwise);
- every number it holds (:func:`check_finite`): finite (TOML and JSON both spell NaN and infinity);
- the raw tables (:func:`check_tables`, before the profile is derived): element counts, samples, chirps, pads, angle
  bins, objects per frame, track life, and the cube and ADC frame they make together;
- the derived profile (:func:`check_profile`, from ``RadarProfile.__post_init__``): the same bounds on the bins,
  every float finite, and the tracker's settings as its configuration takes them (a bad ``[tracking]`` table
  refuses the radar where it is loaded, never a frame at a time; the service also builds the configuration at
  start-up).

New profile keys need nothing here to be finite; a key that sizes an array adds its bound to :data:`TABLE_BOUNDS`.
"""

from __future__ import annotations

import math
from typing import Any

from radar.errors import UserError

MAX_FILE_BYTES = 1 << 20  # a profile file (the largest shipped one is a few KB)
MAX_NESTING = 32  # arrays and tables inside one another in a profile file
MAX_BINS = 4096  # range, angle or Doppler bins of the cube (CARRADA: 256 x 256 x 64)
MAX_ELEMENTS = 64  # transmitters or receivers
MAX_PAD = 16  # zero-padding factor of the range or Doppler FFT
MAX_CUBE_VOXELS = 1 << 25  # R x A x D (256 MiB as complex64): 8x CARRADA's cube
MAX_ADC_SAMPLES = 1 << 25  # samples x chirps x virtual elements of one frame
MAX_OBJECTS_PER_FRAME = 64  # the simulator's objects in one frame
MAX_TRACK_FRAMES = 1000  # confirm_hits, max_misses, tentative_max_misses (a track's life in frames)
MAX_CLASSES = 254  # foreground classes (labels are uint8, background 0)
MAX_NAME_CHARS = 128  # the radar's name and each class name

# (table, key): the range of a physical quantity in SI units ("" the top level), as wide as any FMCW radar goes; a
# carrier of 1e-300 Hz gave range bins of 1.9e301 m. Slopes are bounded in magnitude (a down-chirp is negative).
PHYSICAL_BOUNDS: dict[tuple[str, str], tuple[float, float, str]] = {
    ("chirp", "carrier_hz"): (1e9, 3e11, "1 to 300 GHz"),
    ("chirp", "slope_hz_per_s"): (1e9, 1e15, "1e-3 to 1e3 MHz/us in magnitude"),
    ("chirp", "sweep_bandwidth_hz"): (1e5, 1e11, "0.1 MHz to 100 GHz"),
    ("chirp", "sample_rate_hz"): (1e4, 1e10, "10 ksps to 10 Gsps"),
    ("chirp", "chirp_cycle_s"): (1e-7, 1.0, "0.1 us to 1 s"),
    ("", "frame_rate_hz"): (0.01, 1e4, "0.01 to 10,000 frames a second"),
}

# (table, key): the largest value it may hold (integers that size arrays)
TABLE_BOUNDS: dict[tuple[str, str], int] = {
    ("chirp", "samples_per_chirp"): MAX_BINS, ("chirp", "chirps_per_frame"): MAX_BINS,
    ("array", "n_tx"): MAX_ELEMENTS, ("array", "n_rx"): MAX_ELEMENTS,
    ("processing", "range_pad"): MAX_PAD, ("processing", "doppler_pad"): MAX_PAD,
    ("processing", "angle_bins"): MAX_BINS,
    ("tracking", "confirm_hits"): MAX_TRACK_FRAMES, ("tracking", "max_misses"): MAX_TRACK_FRAMES,
    ("tracking", "tentative_max_misses"): MAX_TRACK_FRAMES,
}


class LimitError(UserError, ValueError):
    """A profile value past its bound (the message names the key, the value and the bound)."""


def _refuse(source: str, key: str, value: Any, bound: str) -> LimitError:
    shown = repr(value) if not isinstance(value, str) else ascii(value[:64])
    return LimitError(f"{source}: {key} = {shown} is out of bounds: {bound}")


def nesting_depth(text: str) -> int:
    """The deepest nesting of ``[`` and ``{`` outside strings and comments in TOML or JSON text."""
    depth = deepest = i = 0
    quote = ""
    while i < len(text):
        if quote:  # inside a string: find its end (basic strings have backslash escapes)
            if text[i] == "\\" and quote[0] == '"':
                i += 2
            elif text.startswith(quote, i):
                i, quote = i + len(quote), ""
            else:
                i += 1
            continue
        ch = text[i]
        if ch == "#":
            end = text.find("\n", i)
            i = len(text) if end < 0 else end
            continue
        if ch in "\"'":
            quote = text[i:i + 3] if text.startswith(ch * 3, i) else ch
            i += len(quote)
            continue
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth = max(0, depth - 1)
        i += 1
    return deepest


def check_text(text: str, source: str) -> None:
    """LimitError for a profile file too large or nested too deep (checked before it is parsed)."""
    if len(text) > MAX_FILE_BYTES:
        raise LimitError(f"{source}: {len(text)} characters, a profile file holds at most {MAX_FILE_BYTES}")
    if (depth := nesting_depth(text)) > MAX_NESTING:
        raise LimitError(f"{source}: arrays or tables nested {depth} deep, at most {MAX_NESTING}")


def check_finite(data: Any, source: str) -> None:
    """LimitError naming the first NaN or infinite number in a parsed profile (tables, arrays), and for nesting
    deeper than MAX_NESTING (a profile handed over already parsed, e.g. from a checkpoint)."""
    stack: list[tuple[str, Any, int]] = [("", data, 0)]
    while stack:
        key, value, depth = stack.pop()
        if depth > MAX_NESTING:
            raise LimitError(f"{source}: {key or 'profile'} is nested more than {MAX_NESTING} deep")
        if isinstance(value, dict):
            stack += [(f"{key}.{k}" if key else str(k), v, depth + 1) for k, v in value.items()]
        elif isinstance(value, list | tuple):
            stack += [(f"{key}[{i}]", v, depth + 1) for i, v in enumerate(value)]
        elif isinstance(value, float) and not math.isfinite(value):
            raise _refuse(source, key, value, "a finite number")


def _integer(table: Any, key: str) -> int | None:
    value = table.get(key) if isinstance(table, dict) else None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def read_checked(path: Any, source: str) -> str:
    """The text of a profile file, refused (LimitError) when too large (before it is read) or nested too deep."""
    if (size := path.stat().st_size) > MAX_FILE_BYTES:
        raise LimitError(f"{source}: {size} bytes, a profile file holds at most {MAX_FILE_BYTES}")
    text = path.read_text()
    check_text(text, source)
    return text


def _check_names(data: dict[str, Any], source: str) -> None:
    names = data.get("class_names")
    if isinstance(names, list) and len(names) > MAX_CLASSES:
        raise _refuse(source, "class_names", f"{len(names)} names", f"at most {MAX_CLASSES} classes")
    listed = names if isinstance(names, list) else []
    for key, name in [("name", data.get("name")), *(("class_names", n) for n in listed)]:
        if isinstance(name, str) and len(name) > MAX_NAME_CHARS:
            raise _refuse(source, key, name, f"at most {MAX_NAME_CHARS} characters")


def check_physical(value: float, key: str, source: str) -> None:
    """LimitError for a physical quantity (a key of :data:`PHYSICAL_BOUNDS`, SI units) out of its range."""
    (low, high, described), = (bound for (_, name), bound in PHYSICAL_BOUNDS.items() if name == key)
    if not low <= abs(value) <= high:
        raise _refuse(source, key, value, f"{described} ([{low:g}, {high:g}])")


def check_tables(data: dict[str, Any], source: str) -> None:
    """LimitError for a raw profile table value past its bound, or a cube or ADC frame too large, before the
    profile is derived (a tdm_order of n_tx entries is built from it)."""
    check_finite(data, source)
    _check_names(data, source)
    for table, key in PHYSICAL_BOUNDS:
        values = data.get(table) if table else data
        value = values.get(key) if isinstance(values, dict) else None
        if isinstance(value, int | float) and not isinstance(value, bool):
            check_physical(float(value), key, source)
    for (table, key), bound in TABLE_BOUNDS.items():
        value = _integer(data.get(table), key)
        if value is not None and value > bound:
            raise _refuse(source, f"[{table}] {key}", value, f"at most {bound}")
    simulation = data.get("simulation")
    objects = simulation.get("objects_per_frame") if isinstance(simulation, dict) else None
    if isinstance(objects, list) and any(isinstance(v, int) and v > MAX_OBJECTS_PER_FRAME for v in objects):
        raise _refuse(source, "[simulation] objects_per_frame", objects, f"at most {MAX_OBJECTS_PER_FRAME} objects")
    sizes = {key: _integer(data.get(table), key) or 1 for table, key in TABLE_BOUNDS if table != "tracking"}
    voxels = (sizes["samples_per_chirp"] * sizes["range_pad"] * sizes["angle_bins"] * sizes["chirps_per_frame"]
              * sizes["doppler_pad"])
    if voxels > MAX_CUBE_VOXELS:
        raise _refuse(source, "the cube (samples x range_pad x angle_bins x chirps x doppler_pad)", voxels,
                      f"at most {MAX_CUBE_VOXELS} voxels")
    adc = sizes["samples_per_chirp"] * sizes["chirps_per_frame"] * sizes["n_tx"] * sizes["n_rx"]
    if adc > MAX_ADC_SAMPLES:
        raise _refuse(source, "the ADC frame (samples x chirps x n_tx x n_rx)", adc, f"at most {MAX_ADC_SAMPLES}")


def check_profile(profile: Any) -> None:
    """LimitError for a derived profile past a bound (RadarProfile.__post_init__ calls this): bins, elements,
    pads, cube and ADC sizes, objects per frame, every float finite, and the tracker built from it."""
    source = f"profile {ascii(profile.name)}"
    for key, bound in (("n_range", MAX_BINS), ("n_angle", MAX_BINS), ("n_doppler", MAX_BINS), ("n_tx", MAX_ELEMENTS),
                       ("n_rx", MAX_ELEMENTS), ("range_pad", MAX_PAD), ("doppler_pad", MAX_PAD)):
        if getattr(profile, key) > bound:
            raise _refuse(source, key, getattr(profile, key), f"at most {bound}")
    n_range, n_angle, n_doppler = profile.shape
    if n_range * n_angle * n_doppler > MAX_CUBE_VOXELS:
        raise _refuse(source, "the cube (R x A x D)", profile.shape, f"at most {MAX_CUBE_VOXELS} voxels")
    if profile.n_samples * profile.n_chirps * profile.n_virtual > MAX_ADC_SAMPLES:
        raise _refuse(source, "the ADC frame (samples x chirps x virtual elements)",
                      profile.n_samples * profile.n_chirps * profile.n_virtual, f"at most {MAX_ADC_SAMPLES}")
    for key in ("range_res", "velocity_res", "carrier_hz", "frame_rate_hz", "max_angle_deg", "snr_0dbsm_10m_db",
                "noise_floor_db", "channel_phase_error_deg", "channel_gain_error_db"):
        if not math.isfinite(getattr(profile, key)):
            raise _refuse(source, key, getattr(profile, key), "a finite number")
    check_physical(profile.carrier_hz, "carrier_hz", source)
    check_physical(profile.frame_rate_hz, "frame_rate_hz", source)
    if profile.objects_per_frame[1] > MAX_OBJECTS_PER_FRAME:
        raise _refuse(source, "objects_per_frame", profile.objects_per_frame,
                      f"at most {MAX_OBJECTS_PER_FRAME} objects")
    check_finite({"tracking": dict(profile.tracking), "region_growing": dict(profile.region_growing)}, source)
    check_tracking(dict(profile.tracking), source)


def check_tracking(tracking: dict[str, Any], source: str) -> None:
    """The ``[tracking]`` values as radar.tracking.TrackerConfig takes them (which radar.profiles cannot import:
    it reads profiles): numbers finite and > 0, ``confirm_hits`` at least 1, every count within its bound. The
    service builds the configuration itself at start-up too (service.radar_check)."""
    for key, value in tracking.items():
        bound = TABLE_BOUNDS.get(("tracking", key))
        if bound is None:
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise _refuse(source, f"[tracking] {key}", value, "a finite number > 0")
        elif not (isinstance(value, int) and (1 if key == "confirm_hits" else 0) <= value <= bound):
            raise _refuse(source, f"[tracking] {key}", value,
                          f"a whole number of frames in [{1 if key == 'confirm_hits' else 0}, {bound}]")
