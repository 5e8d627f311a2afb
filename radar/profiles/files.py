"""Radar profiles as files: the chirp, array and processing parameters of a radar in TOML (or JSON),
from which every derived quantity is computed and checked.

A file holds these tables (units in the key names; see radar/profiles/presets/*.toml for complete examples)::

    name, class_names, frame_rate_hz
    [chirp]       carrier_hz, sweep_bandwidth_hz (sampled) or slope_hz_per_s, sample_rate_hz,
                  samples_per_chirp, chirps_per_frame (chirp cycles), chirp_cycle_s (per TX)
    [array]       n_tx, n_rx, tdm_order (TX firing order in a cycle; virtual element = tx * n_rx + rx)
    [processing]  range_pad, doppler_pad, angle_bins, window ("hann" or "rect")
    [simulation]  noise_floor_db, snr_0dbsm_10m_db, objects_per_frame, max_angle_deg,   (optional)
                  channel_phase_error_deg, channel_gain_error_db (an uncalibrated radar's channel mismatch,
                  standard deviations per virtual channel; radar/simulate/channels.py)
    [expect]      range_res_m, velocity_res_mps, max_range_m, max_velocity_mps          (optional)
    [region_growing]  distance_m, min_snr_db, intensity_ratio, bridge, seed_search      (optional; derive them
                  for a new radar with ``radarseg radar tune-growing PROFILE``)
    [tracking]    any of TRACKING_KEYS (optional: radar.tracking.TrackerConfig's noise levels, gates and track
                  life; the frame period and the unambiguous velocity always come from the radar)
    [scene]       range_m, classes, speed_mps, min_separation_m, walls, wall_range_m, furniture   (optional:
                  indoor scenes at the radar's scale for the simulator; radar/profiles/scene_settings.py)

Derived: range bin = c / (2 B) / range_pad with B = slope * samples / sample_rate; velocity bin =
lambda / (2 chirps chirp_cycle) / doppler_pad; cube = (samples * range_pad, angle_bins, chirps *
doppler_pad). A profile is refused, with the reason, when its parameters contradict each other:
unknown keys, a slope and a bandwidth that disagree, a chirp cycle too short to fire every TX with its
ADC window, an angle FFT smaller than the array, a TDM order that is not a permutation, or ``[expect]``
figures the chirp cannot give (e.g. a sampled bandwidth that cannot give the stated range resolution).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from radar.errors import UserError
from radar.profiles import hardware
from radar.profiles.limits import check_tables, read_checked
from radar.profiles.profile import SPEED_OF_LIGHT, ChirpParameters, RadarProfile
from radar.profiles.scene_settings import SCENE_KEYS, scene_from_table

WINDOWS = ("hann", "rect")
EXPECT_TOLERANCE = 0.005  # relative


class ProfileError(UserError):
    """A radar profile file that is missing, malformed or physically inconsistent."""


CHANNEL_ERROR_BOUNDS = {"channel_phase_error_deg": 90.0, "channel_gain_error_db": 10.0}  # [simulation], at most
_SCHEMA: dict[str, set[str]] = {
    "": {"name", "class_names", "frame_rate_hz", "chirp", "array", "processing", "simulation", "expect",
         "region_growing", "tracking", "scene"},
    "chirp": {"carrier_hz", "sweep_bandwidth_hz", "slope_hz_per_s", "sample_rate_hz", "samples_per_chirp",
              "chirps_per_frame", "chirp_cycle_s"},
    "array": {"n_tx", "n_rx", "tdm_order"},
    "processing": {"range_pad", "doppler_pad", "angle_bins", "window"},
    "simulation": {"noise_floor_db", "snr_0dbsm_10m_db", "objects_per_frame", "max_angle_deg",
                   *CHANNEL_ERROR_BOUNDS},
    "expect": {"range_res_m", "velocity_res_mps", "max_range_m", "max_velocity_mps"},
    "region_growing": {"distance_m", "min_snr_db", "intensity_ratio", "bridge", "seed_search"},
}
TRACKING_FLOATS = ("range_sigma_m", "azimuth_sigma_rad", "min_position_sigma_m", "radial_velocity_sigma_mps",
                   "acceleration_sigma_mps2", "initial_speed_sigma_mps", "gate_chi2", "gate_m")
TRACKING_COUNTS = ("confirm_hits", "max_misses", "tentative_max_misses")
TRACKING_KEYS = TRACKING_FLOATS + TRACKING_COUNTS
"""What a profile's ``[tracking]`` table may set (fields of ``radar.tracking.TrackerConfig``; ranges checked there)."""
_SCHEMA["tracking"] = set(TRACKING_KEYS)
# A real radar's hardware (radar/profiles/hardware.py): TI's chirp timing, antenna positions, calibration, capture.
_SCHEMA[""] |= {"calibration", "capture"}
_SCHEMA["chirp"] |= set(hardware.CHIRP_KEYS)
_SCHEMA["array"] |= set(hardware.ARRAY_KEYS)
_SCHEMA["calibration"], _SCHEMA["capture"] = set(hardware.CALIBRATION_KEYS), set(hardware.CAPTURE_KEYS)
_SCHEMA["scene"] = set(SCENE_KEYS)  # indoor scenes at the radar's scale (checked by scene_settings.scene_from_table)


def _table(data: dict, key: str, source: str, required: bool = True) -> dict:
    table = data.get(key, None)
    if table is None:
        if required:
            raise ProfileError(f"{source}: missing table [{key}]")
        return {}
    if not isinstance(table, dict):
        raise ProfileError(f"{source}: [{key}] must be a table")
    unknown = set(table) - _SCHEMA[key]
    if unknown:
        raise ProfileError(f"{source}: unknown key(s) {sorted(unknown)} in [{key}]; expected {sorted(_SCHEMA[key])}")
    return table


def _number(table: dict, key: str, source: str, *, integer: bool = False, positive: bool = True) -> Any:
    if key not in table:
        raise ProfileError(f"{source}: missing {key}")
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or (integer and not isinstance(value, int)):
        raise ProfileError(f"{source}: {key} must be {'an integer' if integer else 'a number'}, got {value!r}")
    if positive and value <= 0:
        raise ProfileError(f"{source}: {key} must be > 0, got {value!r}")
    return value


def _swept_bandwidth(chirp: dict, adc_time: float, source: str) -> float:
    """The bandwidth swept during the ADC window (Hz), from ``sweep_bandwidth_hz`` or ``slope_hz_per_s`` (both: they
    must agree)."""
    if "sweep_bandwidth_hz" in chirp:
        bandwidth = _number(chirp, "sweep_bandwidth_hz", source)
        if "slope_hz_per_s" in chirp:
            slope_bandwidth = _number(chirp, "slope_hz_per_s", source) * adc_time
            if abs(slope_bandwidth / bandwidth - 1) > EXPECT_TOLERANCE:
                raise ProfileError(
                    f"{source}: slope {chirp['slope_hz_per_s']:.4g} Hz/s over the {adc_time * 1e6:.3g} us ADC window "
                    f"sweeps {slope_bandwidth / 1e6:.4g} MHz, but sweep_bandwidth_hz says {bandwidth / 1e6:.4g} MHz")
        return bandwidth
    if "slope_hz_per_s" in chirp:
        return _number(chirp, "slope_hz_per_s", source) * adc_time
    raise ProfileError(f"{source}: [chirp] needs sweep_bandwidth_hz (sampled) or slope_hz_per_s")


def _check_expected(expect: dict, derived: dict[str, float], source: str, basis: str) -> None:
    """ProfileError unless every ``[expect]`` figure matches the derived one within :data:`EXPECT_TOLERANCE`."""
    for key in expect:
        stated = _number(expect, key, source)
        if abs(derived[key] / stated - 1) > EXPECT_TOLERANCE:
            raise ProfileError(
                f"{source}: [expect] {key} = {stated:.5g}, but the chirp gives {derived[key]:.5g} ({basis})")


def _simulation_options(simulation: dict, source: str) -> dict[str, Any]:
    """The ``[simulation]`` table as RadarProfile keyword arguments."""
    sim_kwargs: dict[str, Any] = {}
    for key in ("noise_floor_db", "snr_0dbsm_10m_db", "max_angle_deg"):
        if key in simulation:
            sim_kwargs[key] = float(_number(simulation, key, source, positive=key != "noise_floor_db"))
    if "objects_per_frame" in simulation:
        lo_hi = simulation["objects_per_frame"]
        if not (isinstance(lo_hi, list) and len(lo_hi) == 2 and all(isinstance(v, int) for v in lo_hi)):
            raise ProfileError(f"{source}: objects_per_frame must be [min, max] integers")
        sim_kwargs["objects_per_frame"] = tuple(lo_hi)
    for key, most in CHANNEL_ERROR_BOUNDS.items():
        if key in simulation:
            value = float(_number(simulation, key, source, positive=False))
            if not 0 <= value <= most:
                raise ProfileError(f"{source}: [simulation] {key} = {value:g}, expected a standard deviation "
                                   f"between 0 and {most:g}")
            sim_kwargs[key] = value
    return sim_kwargs


def _region_growing_options(table: dict, source: str) -> tuple[tuple[str, Any], ...]:
    """The ``[region_growing]`` table as sorted ``(key, value)`` pairs (checked here; ranges by the config)."""
    options: dict[str, Any] = {}
    for key in ("distance_m", "min_snr_db"):
        if key in table:
            options[key] = float(_number(table, key, source))
    if "intensity_ratio" in table:
        ratio = float(_number(table, "intensity_ratio", source, positive=False))
        if not 0.0 <= ratio <= 1.0:
            raise ProfileError(f"{source}: [region_growing] intensity_ratio must be in [0, 1], got {ratio}")
        options["intensity_ratio"] = ratio
    if "bridge" in table:
        bridge = table["bridge"]
        if isinstance(bridge, bool) or not isinstance(bridge, int) or bridge < 0:
            raise ProfileError(f"{source}: [region_growing] bridge must be a gap size in voxels >= 0, got {bridge!r}")
        options["bridge"] = bridge
    if "seed_search" in table:
        search = table["seed_search"]
        if not (isinstance(search, list) and len(search) == 3
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in search)):
            raise ProfileError(f"{source}: [region_growing] seed_search must be 3 integers >= 0 (range, angle, "
                               f"Doppler bins), got {search!r}")
        options["seed_search"] = tuple(search)
    return tuple(sorted(options.items()))


def _tracking_options(table: dict, source: str) -> tuple[tuple[str, float | int], ...]:
    """The ``[tracking]`` table as sorted ``(key, value)`` pairs: positive numbers, whole counts >= 0."""
    options: dict[str, float | int] = {}
    for key in TRACKING_FLOATS:
        if key in table:
            options[key] = float(_number(table, key, source))
    for key in TRACKING_COUNTS:
        if key in table:
            value = table[key]
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ProfileError(f"{source}: [tracking] {key} must be a whole number of frames >= 0, got {value!r}")
            options[key] = value
    return tuple(sorted(options.items()))


def _scene_options(data: dict, class_names: tuple[str, ...], max_range_m: float, source: str):
    """The ``[scene]`` table as :class:`~radar.profiles.scene_settings.SceneSettings`, or None when absent."""
    if "scene" not in data:
        return None
    if not isinstance(data["scene"], dict):
        raise ProfileError(f"{source}: [scene] must be a table")
    try:
        return scene_from_table(data["scene"], class_names, max_range_m)
    except ValueError as exc:
        raise ProfileError(f"{source}: {exc}") from None


def _hardware(data: dict, chirp: dict, array: dict, n_virtual: int, adc_time: float, cycle: float | None,
              source: str) -> tuple:
    """(chirp cycle, ChirpParameters timing kwargs, antenna positions, calibration, capture) of a real radar's
    hardware keys (radar/profiles/hardware.py)."""
    try:
        cycle, timing = hardware.chirp_timing(chirp, int(array["n_tx"]), adc_time, cycle)
        return (cycle, timing, hardware.antenna_positions(array, n_virtual),
                hardware.calibration(_table(data, "calibration", source, False), n_virtual),
                hardware.capture(_table(data, "capture", source, False)))
    except ValueError as exc:
        raise ProfileError(f"{source}: {exc}") from None


def profile_from_dict(data: dict[str, Any], *, source: str = "profile") -> RadarProfile:
    """Validate a profile description and build the :class:`RadarProfile` it derives."""
    if not isinstance(data, dict):
        raise ProfileError(f"{source}: expected a table of profile parameters")
    unknown = set(data) - _SCHEMA[""]
    if unknown:
        raise ProfileError(f"{source}: unknown key(s) {sorted(unknown)}; expected {sorted(_SCHEMA[''])}")
    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise ProfileError(f"{source}: name must be a non-empty string")
    class_names = data.get("class_names")
    if not (isinstance(class_names, list) and class_names and all(isinstance(c, str) and c for c in class_names)):
        raise ProfileError(f"{source}: class_names must be a non-empty list of names (background is implicit)")
    check_tables(data, source)  # radar.profiles.limits: bounds and finite numbers before anything is derived
    chirp, array = _table(data, "chirp", source), _table(data, "array", source)
    processing, simulation = _table(data, "processing", source), _table(data, "simulation", source, False)
    expect = _table(data, "expect", source, False)
    growing = _region_growing_options(_table(data, "region_growing", source, False), source)
    tracking = _tracking_options(_table(data, "tracking", source, False), source)

    carrier = _number(chirp, "carrier_hz", source)
    fs = _number(chirp, "sample_rate_hz", source)
    samples = _number(chirp, "samples_per_chirp", source, integer=True)
    chirps = _number(chirp, "chirps_per_frame", source, integer=True)
    cycle = _number(chirp, "chirp_cycle_s", source) if "chirp_cycle_s" in chirp else None
    adc_time = samples / fs
    bandwidth = _swept_bandwidth(chirp, adc_time, source)

    n_tx = _number(array, "n_tx", source, integer=True)
    n_rx = _number(array, "n_rx", source, integer=True)
    tdm_order = tuple(array.get("tdm_order", range(n_tx)))
    if sorted(tdm_order) != list(range(n_tx)):
        raise ProfileError(f"{source}: tdm_order {list(tdm_order)} must be a permutation of 0..{n_tx - 1}")
    cycle, timing, positions, calibration, capture = _hardware(data, chirp, array, n_tx * n_rx, adc_time, cycle, source)
    if cycle < n_tx * adc_time:
        raise ProfileError(
            f"{source}: a chirp cycle of {cycle * 1e6:.3g} us cannot fire {n_tx} TX chirps of "
            f"{adc_time * 1e6:.3g} us ADC sampling each (needs >= {n_tx * adc_time * 1e6:.3g} us)")

    range_pad = _number(processing, "range_pad", source, integer=True)
    doppler_pad = _number(processing, "doppler_pad", source, integer=True)
    angle_bins = _number(processing, "angle_bins", source, integer=True)
    window = processing.get("window", "hann")
    if window not in WINDOWS:
        raise ProfileError(f"{source}: window {window!r}, expected one of {list(WINDOWS)}")
    if angle_bins < n_tx * n_rx:
        raise ProfileError(f"{source}: angle_bins ({angle_bins}) must be >= the virtual array ({n_tx * n_rx})")

    wavelength = 299_792_458.0 / carrier
    range_res = SPEED_OF_LIGHT / (2 * bandwidth) / range_pad
    velocity_res = wavelength / (2 * chirps * cycle) / doppler_pad
    derived = {"range_res_m": range_res, "velocity_res_mps": velocity_res,
               "max_range_m": range_res * samples * range_pad,
               "max_velocity_mps": velocity_res * chirps * doppler_pad / 2}
    _check_expected(expect, derived, source, f"sampled bandwidth {bandwidth / 1e6:.4g} MHz, {chirps} chirps of "
                    f"{cycle * 1e6:.4g} us, pads {range_pad}/{doppler_pad}")

    sim_kwargs = _simulation_options(simulation, source)
    scene = _scene_options(data, tuple(class_names), derived["max_range_m"], source)
    frame_rate = float(_number(data, "frame_rate_hz", source)) if "frame_rate_hz" in data else 10.0
    try:
        return RadarProfile(
            name=name, n_range=samples * range_pad, n_angle=angle_bins, n_doppler=chirps * doppler_pad,
            range_res=range_res, velocity_res=velocity_res, n_tx=n_tx, n_rx=n_rx,
            class_names=tuple(class_names), range_pad=range_pad, doppler_pad=doppler_pad, carrier_hz=float(carrier),
            frame_rate_hz=frame_rate, window=window, region_growing=growing, tracking=tracking,
            chirp=ChirpParameters(float(carrier), float(bandwidth), float(fs), samples, chirps, float(cycle),
                                  tdm_order, window, **timing),
            antenna_positions=positions, calibration=calibration, capture=capture,
            **sim_kwargs, **({"extra": {"scene": scene}} if scene is not None else {}),
        )
    except ValueError as exc:
        raise ProfileError(f"{source}: {exc}") from None


def load_profile_file(path: str | Path) -> RadarProfile:
    """A profile from a ``.toml`` or ``.json`` file."""
    path = Path(path)
    if not path.is_file():
        raise ProfileError(f"{path}: no such profile file")
    try:
        if path.suffix == ".json":
            data = json.loads(read_checked(path, str(path)))
        elif path.suffix == ".toml":
            data = tomllib.loads(read_checked(path, str(path)))
        else:
            raise ProfileError(f"{path}: profile files are .toml or .json")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ProfileError(f"{path}: not valid {path.suffix[1:].upper()} ({exc})") from None
    return profile_from_dict(data, source=str(path))


def describe(profile: RadarProfile) -> list[tuple[str, str]]:
    """(quantity, value) rows of everything a profile derives, for ``radarseg radar show``."""
    rows = [("name", profile.name), ("cube (R x A x D)", " x ".join(map(str, profile.shape))),
            ("classes", ", ".join(profile.all_class_names)),
            ("range bin / resolution", f"{profile.range_res:.4f} m / {profile.range_resolution:.4f} m"),
            ("max range", f"{profile.max_range:.2f} m"),
            ("velocity bin / resolution", f"{profile.velocity_res:.4f} / {profile.velocity_resolution:.4f} m/s"),
            ("max |radial velocity|", f"{profile.max_velocity:.2f} m/s"),
            ("virtual array", f"{profile.n_tx} TX x {profile.n_rx} RX = {profile.n_virtual} elements"),
            ("angle resolution (broadside)", f"{2 / profile.n_virtual:.4f} in sin(theta)"),
            ("sampled bandwidth", f"{profile.sampled_bandwidth_hz / 1e6:.2f} MHz"),
            ("chirp cycle", f"{profile.chirp_cycle_s * 1e6:.2f} us"),
            ("carrier", f"{profile.carrier_hz / 1e9:.2f} GHz"),
            ("frame rate", f"{profile.frame_rate_hz:.1f} Hz")]
    if profile.chirp is not None:
        c = profile.chirp
        rows += [("ADC", f"{c.samples_per_chirp} samples at {c.sample_rate_hz / 1e6:.2f} MHz "
                         f"({c.adc_time_s * 1e6:.2f} us)"),
                 ("slope", f"{c.slope_hz_per_s / 1e12:.3f} MHz/us"), ("TDM order", str(list(c.tdm_order))),
                 ("window", c.window)]
    growing = ", ".join(f"{k} {list(v) if isinstance(v, tuple) else v}" for k, v in profile.region_growing)
    rows.append(("region growing", growing or "not stated: the paper's settings are assumed "
                                              "(radarseg radar tune-growing derives them)"))
    tracking = ", ".join(f"{k} {v}" for k, v in profile.tracking)
    rows.append(("tracking", tracking or "derived from the radar (radar.tracking.TrackerConfig.for_profile)"))
    scene = profile.extra.get("scene")
    if scene is not None:
        rows.append(("scene", f"objects at {scene.range_m[0]:g}-{scene.range_m[1]:g} m: "
                              + ", ".join(f"{name} {lo}-{hi}" for name, (lo, hi) in scene.classes)
                              + f"; walls {scene.walls[0]}-{scene.walls[1]}, "
                              f"furniture {scene.furniture[0]}-{scene.furniture[1]}"))
    if profile.has_channel_errors:
        rows.append(("simulated channel errors", f"{profile.channel_phase_error_deg:g} deg, "
                                                 f"{profile.channel_gain_error_db:g} dB (standard deviations)"))
    return rows + hardware.describe_rows(profile)


def profile_to_dict(profile: RadarProfile) -> dict[str, Any]:
    """The file form of a profile (what :func:`profile_from_dict` reads back), so recordings, stores
    and checkpoints of a radar described by a file carry their radar with them."""
    if profile.chirp is None:
        raise ProfileError(f"profile {profile.name!r} has no chirp description (it was not loaded from a file)")
    c = profile.chirp
    lo, hi = profile.objects_per_frame
    hardware_tables = hardware.hardware_tables(profile)
    return {
        "name": profile.name, "class_names": list(profile.class_names), "frame_rate_hz": profile.frame_rate_hz,
        "chirp": {"carrier_hz": c.carrier_hz, "sweep_bandwidth_hz": c.sweep_bandwidth_hz,
                  "sample_rate_hz": c.sample_rate_hz, "samples_per_chirp": c.samples_per_chirp,
                  "chirps_per_frame": c.chirps_per_frame, "chirp_cycle_s": c.chirp_cycle_s, **hardware_tables["chirp"]},
        "array": {"n_tx": profile.n_tx, "n_rx": profile.n_rx, "tdm_order": list(c.tdm_order),
                  **hardware_tables["array"]},
        "processing": {"range_pad": profile.range_pad, "doppler_pad": profile.doppler_pad,
                       "angle_bins": profile.n_angle, "window": profile.window},
        "simulation": {"noise_floor_db": profile.noise_floor_db, "snr_0dbsm_10m_db": profile.snr_0dbsm_10m_db,
                       "objects_per_frame": [lo, hi], "max_angle_deg": profile.max_angle_deg,
                       **{key: getattr(profile, key) for key in CHANNEL_ERROR_BOUNDS if getattr(profile, key)}},
        **({"region_growing": {k: list(v) if isinstance(v, tuple) else v for k, v in profile.region_growing}}
           if profile.region_growing else {}),
        **({"tracking": dict(profile.tracking)} if profile.tracking else {}),
        **{key: table for key, table in hardware_tables.items() if key not in ("chirp", "array")},
        **({"scene": profile.extra["scene"].to_table()} if profile.extra.get("scene") is not None else {}),
    }
