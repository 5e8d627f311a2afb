"""A radar profile: the chirp and array parameters of a radar and everything derived from them.

A profile fixes the shape of the RAD cube and the meaning of every bin (docs/design.md section 2):

- range bin ``r`` is ``r * range_res`` metres, bin 0 nearest;
- angle bins are uniform in sin(theta): ``sin(theta) = (a - A/2) / (A/2)``, theta > 0 to the right;
- Doppler bin ``d`` is ``(d - D/2) * velocity_res`` m/s, positive = receding;
- Cartesian ``x = range * sin(theta)`` (lateral), ``y = range * cos(theta)`` (forward).

Range and Doppler FFTs may be zero-padded (``range_pad``, ``doppler_pad``): the bin spacing is then
``1/pad`` of the physical resolution, as in the NXP set. The angle FFT is always zero-padded from the
virtual array to ``n_angle`` bins.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from radar.profiles.limits import check_profile

SPEED_OF_LIGHT = 299_792_458.0  # m/s


@dataclass(frozen=True)
class ChirpParameters:
    """The radar's waveform and array, as a profile file states them (SI units)."""

    carrier_hz: float
    sweep_bandwidth_hz: float  # bandwidth swept while the ADC samples
    sample_rate_hz: float
    samples_per_chirp: int
    chirps_per_frame: int  # chirp cycles per frame
    chirp_cycle_s: float  # time between two chirps of the same TX
    tdm_order: tuple[int, ...]
    window: str = "hann"
    # TI's chirp timing, when the file states it (``radarseg radar from-ti``): seconds, None when not stated.
    idle_time_s: float | None = None
    adc_start_time_s: float | None = None
    ramp_end_time_s: float | None = None
    tx_start_time_s: float | None = None
    real_adc: bool = False  # the ADC sampled I only (TI adcCfg format 0): range bins past R/2 mirror the first half

    @property
    def slope_hz_per_s(self) -> float:
        return self.sweep_bandwidth_hz * self.sample_rate_hz / self.samples_per_chirp

    @property
    def adc_time_s(self) -> float:
        return self.samples_per_chirp / self.sample_rate_hz


@dataclass(frozen=True)
class ChannelCalibration:
    """Per-virtual-channel correction of a radar (TI's ``compRangeBiasAndRxChanPhase``): ``coefficients[k]`` multiplies
    virtual element k's samples before the angle FFT; ``range_bias_m`` is carried, not applied to the bins."""

    range_bias_m: float
    coefficients: tuple[complex, ...]


@dataclass(frozen=True)
class RadarProfile:
    """One radar: cube shape, bin spacings and the chirp parameters behind them.

    Conversions accept scalars or arrays and return float64 of the same shape.
    """

    name: str
    n_range: int  # R: range bins after zero-padding
    n_angle: int  # A: angle bins (zero-padded angle FFT)
    n_doppler: int  # D: Doppler bins after zero-padding
    range_res: float  # metres per range bin
    velocity_res: float  # m/s per Doppler bin
    n_tx: int  # transmitters, time-division multiplexed
    n_rx: int  # receivers; virtual array = n_tx * n_rx half-wavelength elements
    class_names: tuple[str, ...]  # foreground classes; label 0 is background
    range_pad: int = 1  # zero-padding factor of the range FFT
    doppler_pad: int = 1  # zero-padding factor of the Doppler FFT
    carrier_hz: float = 77e9
    frame_rate_hz: float = 10.0
    max_angle_deg: float = 60.0  # field of view used by the scene generator
    # Radar-equation calibration: peak SNR (dB, noiseless peak over mean noise per RAD voxel) of a
    # 0 dBsm point target at 10 m, straddle-free. Sets the transmit/antenna gain constant.
    snr_0dbsm_10m_db: float = 45.0
    # Mean thermal-noise power per RAD voxel in dB (10*log10 |I|^2). 58 dB puts the RD view's
    # mean where CARRADA's is (docs/design.md section 3.1).
    noise_floor_db: float = 58.0
    objects_per_frame: tuple[int, int] = (1, 4)
    # Channel mismatch of the simulated radar (radar/simulate/channels.py): standard deviations of each virtual
    # channel's phase (degrees) and gain (dB) errors, drawn per sequence. 0: ideal, calibrated channels.
    channel_phase_error_deg: float = 0.0
    channel_gain_error_db: float = 0.0
    window: str = "hann"  # on range, Doppler and the array
    chirp: ChirpParameters | None = None  # the waveform, when the profile came from a file
    # Region growing's settings for this radar (keys of radar.region_growing.RegionGrowingConfig), as stated in
    # the file's [region_growing] table: part of the radar, because the right disc radius and SNR floor depend
    # on its resolution and noise. Empty: none stated (the paper's settings are assumed, with a warning).
    region_growing: tuple[tuple[str, float | int | tuple[int, ...]], ...] = ()
    # The tracker's settings for this radar (keys of radar.tracking.TrackerConfig but the two the radar gives: frame
    # period and unambiguous velocity), as stated in the file's [tracking] table. Empty: derived from the radar.
    tracking: tuple[tuple[str, float | int], ...] = ()
    # (azimuth, elevation) of each virtual element in half wavelengths, as the file's [array] states them; empty: a
    # uniform line 0 .. K-1 at elevation 0. The angle FFT places each element at its azimuth.
    antenna_positions: tuple[tuple[float, float], ...] = ()
    calibration: ChannelCalibration | None = None  # the file's [calibration], applied by radar.adc.process_adc
    capture: tuple[tuple[str, str | int | bool], ...] = ()  # the file's [capture]: how a capture card stores the ADC
    extra: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("n_range", "n_angle", "n_doppler", "n_tx", "n_rx", "range_pad", "doppler_pad"):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise ValueError(f"RadarProfile.{name} must be a positive int, got {value!r}")
        if self.n_range % self.range_pad or self.n_doppler % self.doppler_pad:
            raise ValueError(
                f"profile {self.name!r}: n_range ({self.n_range}) and n_doppler ({self.n_doppler}) "
                f"must be multiples of range_pad ({self.range_pad}) and doppler_pad ({self.doppler_pad})"
            )
        if self.n_angle < self.n_virtual:
            raise ValueError(
                f"profile {self.name!r}: n_angle ({self.n_angle}) must be >= the virtual array "
                f"({self.n_virtual} elements)"
            )
        if self.range_res <= 0 or self.velocity_res <= 0:
            raise ValueError(f"profile {self.name!r}: range_res and velocity_res must be > 0")
        lo, hi = self.objects_per_frame
        if not 0 <= lo <= hi:
            raise ValueError(f"profile {self.name!r}: objects_per_frame must be (lo, hi) with 0 <= lo <= hi")
        if self.window not in ("hann", "rect"):
            raise ValueError(f"profile {self.name!r}: window must be 'hann' or 'rect', got {self.window!r}")
        for what, values in (("antenna_positions", self.antenna_positions),
                             ("calibration", () if self.calibration is None else self.calibration.coefficients)):
            if values and len(values) != self.n_virtual:
                raise ValueError(f"profile {self.name!r}: {what} holds {len(values)} entries, expected one per "
                                 f"virtual element ({self.n_virtual})")
        check_profile(self)  # radar.profiles.limits: sizes, finite numbers, the tracker's configuration

    # ----------------------------------------------------------------- derived radar parameters
    @property
    def shape(self) -> tuple[int, int, int]:
        """RAD cube shape (R, A, D)."""
        return (self.n_range, self.n_angle, self.n_doppler)

    @property
    def num_classes(self) -> int:
        """Classes including background (label 0)."""
        return len(self.class_names) + 1

    @property
    def all_class_names(self) -> tuple[str, ...]:
        return ("background", *self.class_names)

    @property
    def n_virtual(self) -> int:
        return self.n_tx * self.n_rx

    @property
    def n_samples(self) -> int:
        """ADC samples per chirp (before range zero-padding)."""
        return self.n_range // self.range_pad

    @property
    def n_chirps(self) -> int:
        """Chirp cycles per frame (before Doppler zero-padding); each cycle fires every TX once."""
        return self.n_doppler // self.doppler_pad

    @property
    def wavelength(self) -> float:
        return SPEED_OF_LIGHT / self.carrier_hz

    @property
    def max_range(self) -> float:
        """Unambiguous range covered by the range axis (m)."""
        return self.n_range * self.range_res

    @property
    def max_velocity(self) -> float:
        """Largest |radial velocity| before Doppler aliasing (m/s)."""
        return self.n_doppler / 2 * self.velocity_res

    @property
    def range_resolution(self) -> float:
        """Physical range resolution c / (2 B_sampled) (m); equals range_res * range_pad."""
        return self.range_res * self.range_pad

    @property
    def velocity_resolution(self) -> float:
        """Physical velocity resolution (m/s); equals velocity_res * doppler_pad."""
        return self.velocity_res * self.doppler_pad

    @property
    def sampled_bandwidth_hz(self) -> float:
        """Bandwidth swept while the ADC samples: c / (2 * range resolution)."""
        return SPEED_OF_LIGHT / (2 * self.range_resolution)

    @property
    def chirp_cycle_s(self) -> float:
        """Time between two chirps of the same TX: lambda / (2 * n_chirps * velocity resolution)."""
        return self.wavelength / (2 * self.n_chirps * self.velocity_resolution)

    @property
    def frame_period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    # ----------------------------------------------------------------- bin <-> physical
    def range_m(self, range_bin):
        """Range (m) of a (fractional) range bin."""
        return np.asarray(range_bin, dtype=np.float64) * self.range_res

    def range_bin(self, range_m):
        """Fractional range bin of a range in metres."""
        return np.asarray(range_m, dtype=np.float64) / self.range_res

    def sin_theta(self, angle_bin):
        """sin(theta) of a (fractional) angle bin; theta > 0 is to the right."""
        half = self.n_angle / 2
        return (np.asarray(angle_bin, dtype=np.float64) - half) / half

    def angle_bin_from_sin(self, sin_theta):
        half = self.n_angle / 2
        return np.asarray(sin_theta, dtype=np.float64) * half + half

    def angle_deg(self, angle_bin):
        """Azimuth (degrees) of a (fractional) angle bin."""
        return np.degrees(np.arcsin(np.clip(self.sin_theta(angle_bin), -1.0, 1.0)))

    def angle_bin(self, angle_deg):
        """Fractional angle bin of an azimuth in degrees."""
        return self.angle_bin_from_sin(np.sin(np.radians(np.asarray(angle_deg, dtype=np.float64))))

    def velocity_mps(self, doppler_bin):
        """Radial velocity (m/s, positive receding) of a (fractional) Doppler bin."""
        return (np.asarray(doppler_bin, dtype=np.float64) - self.n_doppler / 2) * self.velocity_res

    def doppler_bin(self, velocity_mps):
        """Fractional Doppler bin of a radial velocity (not wrapped: may fall outside [0, D))."""
        return np.asarray(velocity_mps, dtype=np.float64) / self.velocity_res + self.n_doppler / 2

    def xy(self, range_bin, angle_bin):
        """Cartesian (x lateral, y forward) in metres of (fractional) range and angle bins."""
        rng = self.range_m(range_bin)
        sin_t = np.clip(self.sin_theta(angle_bin), -1.0, 1.0)
        return rng * sin_t, rng * np.sqrt(1.0 - sin_t**2)

    def bins_from_xy(self, x, y):
        """Fractional (range bin, angle bin) of Cartesian points (m)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        rng = np.hypot(x, y)
        sin_t = np.divide(x, rng, out=np.zeros_like(rng), where=rng > 0)
        return self.range_bin(rng), self.angle_bin_from_sin(sin_t)

    @cached_property
    def ra_cartesian(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) in metres of every RA cell centre, each float32 (R, A)."""
        x, y = self.xy(np.arange(self.n_range)[:, None], np.arange(self.n_angle)[None, :])
        return x.astype(np.float32), y.astype(np.float32)

    @property
    def has_channel_errors(self) -> bool:
        """Whether the simulated radar's channels are mismatched (either standard deviation above 0)."""
        return self.channel_phase_error_deg > 0 or self.channel_gain_error_db > 0

    @cached_property
    def fingerprint(self) -> str:
        """Short hash of everything that gives a bin its meaning (cube shape, spacings, array, window,
        chirp): two profiles with the same fingerprint produce interchangeable cubes."""
        key = {k: v for k, v in self.to_dict().items() if k not in ("noise_floor_db", "snr_0dbsm_10m_db")}
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        """Plain-JSON description (radar parameters and derived values) for recordings and stores."""
        chirp = None if self.chirp is None else {
            "carrier_hz": self.chirp.carrier_hz, "sweep_bandwidth_hz": self.chirp.sweep_bandwidth_hz,
            "sample_rate_hz": self.chirp.sample_rate_hz, "samples_per_chirp": self.chirp.samples_per_chirp,
            "chirps_per_frame": self.chirp.chirps_per_frame, "chirp_cycle_s": self.chirp.chirp_cycle_s,
            "tdm_order": list(self.chirp.tdm_order)}
        return {
            "window": self.window,
            "chirp": chirp,
            "name": self.name,
            "shape": list(self.shape),
            "range_res_m": self.range_res,
            "velocity_res_mps": self.velocity_res,
            "range_pad": self.range_pad,
            "doppler_pad": self.doppler_pad,
            "n_tx": self.n_tx,
            "n_rx": self.n_rx,
            "carrier_hz": self.carrier_hz,
            "frame_rate_hz": self.frame_rate_hz,
            "class_names": list(self.class_names),
            "max_range_m": self.max_range,
            "max_velocity_mps": self.max_velocity,
            "sampled_bandwidth_hz": self.sampled_bandwidth_hz,
            "chirp_cycle_s": self.chirp_cycle_s,
            "noise_floor_db": self.noise_floor_db,
            "snr_0dbsm_10m_db": self.snr_0dbsm_10m_db,
            # stated only when not the default, so that the fingerprints of profiles without them stay the same
            **({"antenna_positions": [list(p) for p in self.antenna_positions]} if self.antenna_positions else {}),
            **({"real_adc": True} if self.chirp is not None and self.chirp.real_adc else {}),
        }
