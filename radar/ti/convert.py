"""A TI configuration as a radar profile file (``radarseg radar from-ti``).

The profile states TI's timing as TI states it (start frequency as the carrier, idle, ADC start, ramp end, TX start,
slope, samples, sample rate); the loader derives the sampled bandwidth (slope x samples / rate) and the TDM chirp
cycle (n_tx x (idle + ramp end)). TX indices in the profile number the fired TX by their TX number (the lowest fired
TX is 0); ``tdm_order`` is the chirp table's firing order in those indices. Calibration coefficients are taken in the
SDK's virtual antenna order (the order the chirps fire, then RX) and stored per virtual element ``tx * n_rx + rx``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from radar.profiles import RadarProfile
from radar.profiles.files import profile_from_dict
from radar.profiles.scene_settings import default_scene
from radar.ti.boards import virtual_positions
from radar.ti.cfg import TiConfig, TiConfigError

DEFAULT_CLASSES = ("pedestrian", "cyclist", "car")


def _seconds(microseconds: float) -> float:
    """TI's microseconds in seconds, without binary noise in the file (30 us -> 3e-05, not 2.9999999999999997e-05)."""
    return float(f"{microseconds!r}e-6")


def default_angle_bins(n_virtual: int) -> int:
    """64, or the next power of two that holds the virtual array."""
    return max(64, 1 << (n_virtual - 1).bit_length())


def _calibration_table(cfg: TiConfig, tx_numbers: tuple[int, ...]) -> dict[str, Any] | None:
    if cfg.range_bias_m is None:
        return None
    n_rx = len(cfg.rx_channels)
    needed = len(tx_numbers) * n_rx
    if len(cfg.channel_coefficients) < needed:
        raise TiConfigError(f"compRangeBiasAndRxChanPhase: {len(cfg.channel_coefficients)} (re, im) pairs, the "
                            f"{len(tx_numbers)} TX x {n_rx} RX virtual array needs {needed}")
    pairs = []
    for tx in tx_numbers:  # element k = tx index * n_rx + rx; the SDK's order is the firing slot, then RX
        slot = cfg.tx_fired.index(tx)
        pairs += [cfg.channel_coefficients[slot * n_rx + r] for r in range(n_rx)]
    return {"range_bias_m": cfg.range_bias_m, "channel_coefficients": [[c.real, c.imag] for c in pairs]}


def profile_table(cfg: TiConfig, *, name: str, angle_bins: int | None = None, board: str | None = None,
                  lvds_lanes: int = 2, class_names: tuple[str, ...] = DEFAULT_CLASSES) -> dict[str, Any]:
    """The profile file (as a dict) a TI configuration describes."""
    p = cfg.profile
    tx_numbers = tuple(sorted(cfg.tx_fired))
    n_virtual = len(tx_numbers) * len(cfg.rx_channels)
    array: dict[str, Any] = {"n_tx": len(tx_numbers), "n_rx": len(cfg.rx_channels),
                             "tdm_order": [tx_numbers.index(tx) for tx in cfg.tx_fired]}
    if board is not None:
        positions = virtual_positions(board, tx_numbers, cfg.rx_channels)
        array["virtual_azimuth"] = [float(a) for a, _ in positions]
        array["virtual_elevation"] = [float(e) for _, e in positions]
    data: dict[str, Any] = {
        "name": name, "class_names": list(class_names), "frame_rate_hz": 1000.0 / cfg.frame_period_ms,
        "chirp": {"carrier_hz": p.start_freq_ghz * 1e9, "slope_hz_per_s": p.slope_mhz_per_us * 1e12,
                  "sample_rate_hz": p.sample_rate_ksps * 1e3, "samples_per_chirp": p.samples,
                  "chirps_per_frame": cfg.loops, "idle_time_s": _seconds(p.idle_time_us),
                  "adc_start_time_s": _seconds(p.adc_start_time_us), "ramp_end_time_s": _seconds(p.ramp_end_time_us),
                  "tx_start_time_s": _seconds(p.tx_start_time_us), "adc": "real" if cfg.real_adc else "complex"},
        "array": array,
        "processing": {"range_pad": 1, "doppler_pad": 1,
                       "angle_bins": angle_bins if angle_bins is not None else default_angle_bins(n_virtual),
                       "window": "hann"},
        # SampleSwap 1 (TI's demo configurations for the DCA1000) is read I first by TI's capture scripts
        "capture": {"format": "dca1000", "lvds_lanes": lvds_lanes, "iq_order": "iq" if cfg.sample_swap == 1 else "qi",
                    "offset_binary": False, "adc_bits": cfg.adc_bits},
    }
    if p.slope_mhz_per_us < 0:
        raise TiConfigError(f"profileCfg: a falling ramp (freqSlopeConst {p.slope_mhz_per_us:g}) is not supported")
    calibration = _calibration_table(cfg, tx_numbers)
    if calibration is not None:
        data["calibration"] = calibration
    return data


def ti_figures(cfg: TiConfig) -> dict[str, float]:
    """The radar's figures by TI's formulas (mmWave SDK demo visualizer; c = 3e8 as TI takes it): range resolution
    c fs / (2 S N), maximum range c fs / (2 S) (complex ADC; half for real), velocity resolution
    c / (2 f0 (idle + ramp end) loops n_tx), maximum velocity c / (4 f0 (idle + ramp end) n_tx)."""
    c, p = 3e8, cfg.profile
    fs, slope, f0 = p.sample_rate_ksps * 1e3, p.slope_mhz_per_us * 1e12, p.start_freq_ghz * 1e9
    chirp_s, n_tx = (p.idle_time_us + p.ramp_end_time_us) * 1e-6, len(cfg.tx_fired)
    return {"range_resolution_m": c * fs / (2 * slope * p.samples),
            "max_range_m": c * fs / (2 * slope) / (2 if cfg.real_adc else 1),
            "velocity_resolution_mps": c / (2 * f0 * chirp_s * cfg.loops * n_tx),
            "max_velocity_mps": c / (4 * f0 * chirp_s * n_tx)}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot write {value!r} to a profile file")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):  # an inline table inside a table ([scene] classes = {pedestrian = [1, 3]})
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"no TOML form for {value!r}")


def to_toml(data: dict[str, Any], header: list[str] = ()) -> str:
    """TOML text of a profile dict: top-level keys, then one table per nested dict; ``header`` lines as comments."""
    lines = [f"# {line}" for line in header]
    lines += [f"{key} = {_toml_value(value)}" for key, value in data.items() if not isinstance(value, dict)]
    for key, table in data.items():
        if isinstance(table, dict):
            lines += ["", f"[{key}]"] + [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def write_profile(cfg: TiConfig, out: str | Path, *, source: str, scene: bool = True,
                  **options: Any) -> RadarProfile:
    """Write the profile file of ``cfg`` to ``out`` (.toml) and return the profile it loads as (checked before
    anything is written). With ``scene`` a radar that sees less than the road radars gets a ``[scene]`` table at
    its scale (:func:`radar.profiles.scene_settings.default_scene`: people walking in a room), so that ``simulate``
    puts no car or cyclist at road speeds into a 6 m room; without it, the road scenes."""
    out = Path(out)
    if out.suffix != ".toml":
        raise TiConfigError(f"{out}: the profile is written as .toml")
    data = profile_table(cfg, **options)
    profile = profile_from_dict(data, source=f"{source} (as a profile)")
    indoor = default_scene(profile, person=profile.class_names[0]) if scene else None
    if indoor is not None:
        data["scene"] = indoor.to_table()
        profile = profile_from_dict(data, source=f"{source} (as a profile)")
    figures = ti_figures(cfg)
    header = [f"Radar profile written by `radarseg radar from-ti` from {source}.",
              "TI's figures: " + ", ".join(f"{k} {v:.5g}" for k, v in figures.items()) + "."]
    if cfg.ignored:
        header.append("Ignored (processing chain, monitors): " + " ".join(cfg.ignored))
    if cfg.unknown:
        header.append("Unknown commands, ignored: " + " ".join(cfg.unknown))
    header += list(cfg.notes)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(to_toml(data, header))
    return profile
