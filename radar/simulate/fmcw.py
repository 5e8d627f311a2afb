"""FMCW signal chain: beat-signal synthesis over (sample, chirp, virtual element) and the FFT chain
that turns it into a complex RAD cube in the project's frame (docs/design.md sections 2 and 3.1).

Signal model of point scatterer ``p`` (range ``R_p``, sin(theta) ``s_p``, radial velocity ``v_p``,
complex amplitude ``alpha_p``), ADC sample ``n``, chirp cycle ``m``, virtual element ``k = t*n_rx + q``
(TX ``t``, RX ``q``)::

    x[n, m, k] = sum_p alpha_p * exp(j 2pi f_r n) * exp(j 2pi f_d m) * exp(j pi k s_p) * tdm_{t}
    f_r = (R_p / range_res) / R        beat frequency 2 S R / c, in cycles per sample of the padded FFT
    f_d = (v_p / velocity_res) / D     Doppler phase 4 pi v Tc / lambda per chirp cycle
    tdm_t = exp(j 2pi f_d t / n_tx)    TDM: TX t fires t/n_tx of a cycle later (optional coupling)

The sum is separable: per-axis phasor matrices and one matrix product (no loop over scatterers).
The chain applies Hann windows on range, Doppler and the array, zero-pads each FFT to the cube size
and fftshifts Doppler and angle, so a scatterer peaks at range bin ``R_p/range_res``, angle bin
``A/2 (1 + s_p)`` and Doppler bin ``D/2 + v_p/velocity_res``. Every axis is circular, as the FFTs are.

Because windows and FFTs are linear, the noiseless spectrum of any set of scatterers is exactly
``sum_p alpha_p K_r[p] (x) K_a[p] (x) K_d[p]``, with the 1-D kernels of :func:`axis_kernels`; the
label code uses this to evaluate each object's own response in a window around it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

from radar.adc import adc_to_rad, chain_constants, element_azimuths, tdm_slots
from radar.profiles import RadarProfile, get_profile


@dataclass(frozen=True)
class Scatterers:
    """Point scatterers, all arrays of shape (P,). Positions in metres, velocities in m/s."""

    x: np.ndarray  # lateral (m), > 0 to the right
    y: np.ndarray  # forward (m)
    vx: np.ndarray  # m/s
    vy: np.ndarray  # m/s
    amplitude: np.ndarray  # complex received amplitude (radar equation and phase already applied)

    def __len__(self) -> int:
        return len(self.x)

    @property
    def range_m(self) -> np.ndarray:
        return np.hypot(self.x, self.y)

    @property
    def sin_theta(self) -> np.ndarray:
        rng = self.range_m
        return np.divide(self.x, rng, out=np.zeros_like(rng), where=rng > 0)

    @property
    def radial_velocity(self) -> np.ndarray:
        """Radial velocity (m/s), positive receding."""
        rng = self.range_m
        return np.divide(self.x * self.vx + self.y * self.vy, rng, out=np.zeros_like(rng), where=rng > 0)

    @staticmethod
    def concat(parts: list[Scatterers]) -> Scatterers:
        if not parts:
            empty = np.zeros(0)
            return Scatterers(empty, empty, empty, empty, empty.astype(np.complex128))
        return Scatterers(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                            ("x", "y", "vx", "vy", "amplitude")))


def received_amplitude(profile: RadarProfile, range_m, rcs_dbsm) -> np.ndarray:
    """Radar-equation amplitude ``G sqrt(rcs) / R^2`` (received power falls as 1/R^4)."""
    rng = np.maximum(np.asarray(range_m, dtype=np.float64), 0.1)
    rcs = 10 ** (np.asarray(rcs_dbsm, dtype=np.float64) / 10)
    return chain_constants(profile).radar_constant * np.sqrt(rcs) / rng**2


def _phasor_frequencies(profile: RadarProfile, scat: Scatterers) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-scatterer range and Doppler frequencies (cycles per sample / chirp) and sin(theta)."""
    f_range = scat.range_m / profile.range_res / profile.n_range
    f_doppler = scat.radial_velocity / profile.velocity_res / profile.n_doppler
    return f_range, f_doppler, scat.sin_theta


def _element_phasors(profile: RadarProfile, f_doppler, sin_theta, tdm_coupling: bool,
                     channel_gains: np.ndarray | None = None) -> np.ndarray:
    """(P, K) phasors over the virtual array (each element at its azimuth: the profile's stated positions, else
    0 .. K-1 half wavelengths); a TX firing later in the cycle sees extra Doppler phase; ``channel_gains`` (K,)
    complex: each virtual channel's gain and phase error (radar/simulate/channels.py), None for ideal channels."""
    k = element_azimuths(profile)
    e = np.exp(1j * np.pi * sin_theta[:, None] * k[None, :])
    if tdm_coupling:
        e = e * np.exp(2j * np.pi * f_doppler[:, None] * tdm_slots(profile)[None, :] / profile.n_tx)
    if channel_gains is not None:
        e = e * channel_gains[None, :]
    return e


def synthesize_adc(profile: RadarProfile, scat: Scatterers, *, tdm_coupling: bool = False,
                   noise_rng: np.random.Generator | None = None, channel_gains: np.ndarray | None = None) -> np.ndarray:
    """Beat signal (Ns, Nc, K) complex64 of the scatterers, with thermal noise when ``noise_rng`` and the virtual
    channels' errors when ``channel_gains`` (K,)."""
    ns, nc, nk = profile.n_samples, profile.n_chirps, profile.n_virtual
    if len(scat):
        f_range, f_doppler, sin_t = _phasor_frequencies(profile, scat)
        e_range = np.exp(2j * np.pi * np.arange(ns)[:, None] * f_range[None, :]) * scat.amplitude  # (Ns, P)
        e_chirp = np.exp(2j * np.pi * f_doppler[:, None] * np.arange(nc)[None, :])  # (P, Nc)
        e_elem = _element_phasors(profile, f_doppler, sin_t, tdm_coupling, channel_gains)  # (P, K)
        slow = (e_chirp[:, :, None] * e_elem[:, None, :]).reshape(len(scat), nc * nk)
        adc = (e_range.astype(np.complex64) @ slow.astype(np.complex64)).reshape(ns, nc, nk)
    else:
        adc = np.zeros((ns, nc, nk), np.complex64)
    if noise_rng is not None:
        std = chain_constants(profile).adc_noise_std / np.sqrt(2)
        noise = noise_rng.standard_normal((2, ns, nc, nk), dtype=np.float32) * np.float32(std)
        adc += noise[0] + 1j * noise[1]
    return adc


def axis_kernels(profile: RadarProfile, scat: Scatterers, *, tdm_coupling: bool = False,
                 channel_gains: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact 1-D responses of every scatterer after the FFT chain: (P, R), (P, A), (P, D) complex.

    The noiseless RAD response of the scatterers is ``sum_p amplitude_p * Kr[p] (x) Ka[p] (x) Kd[p]``.
    """
    cc = chain_constants(profile)
    f_range, f_doppler, sin_t = _phasor_frequencies(profile, scat)
    n = np.arange(profile.n_samples)
    k_range = scipy.fft.fft(cc.window_range * np.exp(2j * np.pi * f_range[:, None] * n), n=profile.n_range, axis=1)
    m = np.arange(profile.n_chirps)
    k_doppler = scipy.fft.fftshift(
        scipy.fft.fft(cc.window_doppler * np.exp(2j * np.pi * f_doppler[:, None] * m), n=profile.n_doppler, axis=1),
        axes=1,
    )
    elements = cc.window_array * _element_phasors(profile, f_doppler, sin_t, tdm_coupling, channel_gains)  # (P, K)
    k_angle = scipy.fft.fftshift(scipy.fft.fft(elements, n=profile.n_angle, axis=1), axes=1)
    return k_range, k_angle, k_doppler


def point_target_cube(preset: str | RadarProfile, range_m: float, angle_deg: float, velocity_mps: float,
                      rcs_dbsm: float = 10.0, noise: bool = True, seed: int = 0) -> np.ndarray:
    """Calibration entry point: the RAD cube (R, A, D) complex64 of one point scatterer.

    ``velocity_mps`` is radial (positive receding); the scatterer moves along its line of sight.
    The amplitude follows the radar equation; noise is the profile's thermal noise.
    """
    profile = get_profile(preset)
    theta = np.radians(angle_deg)
    x, y = range_m * np.sin(theta), range_m * np.cos(theta)
    amp = received_amplitude(profile, range_m, rcs_dbsm)
    scat = Scatterers(np.array([x]), np.array([y]), np.array([velocity_mps * np.sin(theta)]),
                      np.array([velocity_mps * np.cos(theta)]), np.array([amp], dtype=np.complex128))
    rng = np.random.default_rng(seed) if noise else None
    return adc_to_rad(profile, synthesize_adc(profile, scat, noise_rng=rng))
