"""FMCW signal chain: beat-signal synthesis over (sample, chirp, virtual element) and the FFT chain
that turns it into a complex RAD cube in the project's frame (SPEC sections 2 and 3.1).

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
from functools import lru_cache

import numpy as np
import scipy.fft

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


SMALL_ARRAY = 16  # up to this many virtual elements the angle DFT is a matrix product, above an FFT


def hann(n: int) -> np.ndarray:
    """Hann window of ``n`` points without the zero end points (matters for an 8-element array)."""
    return np.hanning(n + 2)[1:-1]


@dataclass(frozen=True)
class ChainConstants:
    """Windows and scale factors of a profile's FFT chain (cached per profile)."""

    window_range: np.ndarray  # (Ns,)
    window_doppler: np.ndarray  # (Nc,)
    window_array: np.ndarray  # (K,)
    angle_dft: np.ndarray  # (A, K) complex64: windowed, zero-padded, fftshifted angle DFT
    noise_gain: float  # mean noise power per RAD voxel for unit noise power per ADC sample
    peak_gain: float  # |peak|^2 of a unit-amplitude scatterer on bin centres
    adc_noise_std: float  # thermal noise std per ADC sample (complex) for the profile's noise floor
    radar_constant: float  # G in |alpha| = G sqrt(rcs) / R^2 from the profile's SNR calibration


def window(profile: RadarProfile, n: int) -> np.ndarray:
    """The profile's window over ``n`` points (Hann, or rectangular)."""
    return hann(n) if profile.window == "hann" else np.ones(n)


@lru_cache(maxsize=16)
def chain_constants(profile: RadarProfile) -> ChainConstants:
    w_r, w_d, w_a = (window(profile, n) for n in (profile.n_samples, profile.n_chirps, profile.n_virtual))
    a = np.arange(profile.n_angle)[:, None] - profile.n_angle // 2
    k = np.arange(profile.n_virtual)[None, :]
    angle_dft = (np.exp(-2j * np.pi * a * k / profile.n_angle) * w_a[None, :]).astype(np.complex64)
    noise_gain = float((w_r**2).sum() * (w_d**2).sum() * (w_a**2).sum())
    peak_gain = float((w_r.sum() * w_d.sum() * w_a.sum()) ** 2)
    noise_voxel = 10 ** (profile.noise_floor_db / 10)
    adc_noise_std = float(np.sqrt(noise_voxel / noise_gain))
    # SNR of a 0 dBsm target at 10 m: G^2 / 10^4 * peak_gain / noise_voxel = 10^(snr/10)
    radar_constant = float(np.sqrt(10 ** (profile.snr_0dbsm_10m_db / 10) * noise_voxel * 1e4 / peak_gain))
    return ChainConstants(w_r, w_d, w_a, angle_dft, noise_gain, peak_gain, adc_noise_std, radar_constant)


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


def tdm_slots(profile: RadarProfile) -> np.ndarray:
    """(K,) firing slot within a chirp cycle of each virtual element's TX (element k = tx * n_rx + rx)."""
    order = tuple(range(profile.n_tx)) if profile.chirp is None else profile.chirp.tdm_order
    slot_of_tx = np.argsort(np.asarray(order))
    return slot_of_tx[np.arange(profile.n_virtual) // profile.n_rx]


def _element_phasors(profile: RadarProfile, f_doppler, sin_theta, tdm_coupling: bool) -> np.ndarray:
    """(P, K) phasors over the virtual array; a TX firing later in the cycle sees extra Doppler phase."""
    k = np.arange(profile.n_virtual)
    e = np.exp(1j * np.pi * sin_theta[:, None] * k[None, :])
    if tdm_coupling:
        e = e * np.exp(2j * np.pi * f_doppler[:, None] * tdm_slots(profile)[None, :] / profile.n_tx)
    return e


def synthesize_adc(profile: RadarProfile, scat: Scatterers, *, tdm_coupling: bool = False,
                   noise_rng: np.random.Generator | None = None) -> np.ndarray:
    """Beat signal (Ns, Nc, K) complex64 of the scatterers, with thermal noise when ``noise_rng``."""
    ns, nc, nk = profile.n_samples, profile.n_chirps, profile.n_virtual
    if len(scat):
        f_range, f_doppler, sin_t = _phasor_frequencies(profile, scat)
        e_range = np.exp(2j * np.pi * np.arange(ns)[:, None] * f_range[None, :]) * scat.amplitude  # (Ns, P)
        e_chirp = np.exp(2j * np.pi * f_doppler[:, None] * np.arange(nc)[None, :])  # (P, Nc)
        e_elem = _element_phasors(profile, f_doppler, sin_t, tdm_coupling)  # (P, K)
        slow = (e_chirp[:, :, None] * e_elem[:, None, :]).reshape(len(scat), nc * nk)
        adc = (e_range.astype(np.complex64) @ slow.astype(np.complex64)).reshape(ns, nc, nk)
    else:
        adc = np.zeros((ns, nc, nk), np.complex64)
    if noise_rng is not None:
        std = chain_constants(profile).adc_noise_std / np.sqrt(2)
        noise = noise_rng.standard_normal((2, ns, nc, nk), dtype=np.float32) * np.float32(std)
        adc += noise[0] + 1j * noise[1]
    return adc


def adc_to_rad(profile: RadarProfile, adc: np.ndarray, *, tdm_compensation: bool = False) -> np.ndarray:
    """FFT chain: (Ns, Nc, K) ADC samples -> (R, A, D) complex64 RAD cube in the project's frame.

    The profile's window on every axis; range FFT zero-padded to R; Doppler FFT zero-padded to D and
    fftshifted (zero velocity at D/2); ``tdm_compensation`` removes, per Doppler bin, the phase a TX
    firing later in the chirp cycle adds (exact for unaliased velocities); angle DFT zero-padded to A
    and fftshifted (broadside at A/2), as one batched matrix product writing the (R, A, D) layout
    directly for small arrays, an FFT for large ones.
    """
    expected = (profile.n_samples, profile.n_chirps, profile.n_virtual)
    if adc.shape != expected:
        raise ValueError(f"ADC block for profile {profile.name!r} must have shape {expected}, got {adc.shape}")
    cc = chain_constants(profile)
    x = adc.astype(np.complex64, copy=False)
    x = x * cc.window_range[:, None, None].astype(np.float32)
    x = scipy.fft.fft(x, n=profile.n_range, axis=0)  # (R, Nc, K)
    x = x * cc.window_doppler[None, :, None].astype(np.float32)
    x = scipy.fft.fftshift(scipy.fft.fft(x, n=profile.n_doppler, axis=1), axes=1)  # (R, D, K)
    if tdm_compensation and profile.n_tx > 1:
        f_doppler = (np.arange(profile.n_doppler) - profile.n_doppler // 2) / profile.n_doppler  # cycles/chirp
        x = x * np.exp(-2j * np.pi * f_doppler[:, None] * tdm_slots(profile)[None, :] / profile.n_tx
                       ).astype(np.complex64)[None]
    if profile.n_virtual <= SMALL_ARRAY:
        # (A, K) @ (R, K, D) -> (R, A, D): window, zero-padding and fftshift are in the DFT matrix.
        return np.matmul(cc.angle_dft, x.transpose(0, 2, 1))
    x = x * cc.window_array[None, None, :].astype(np.float32)
    x = scipy.fft.fftshift(scipy.fft.fft(x, n=profile.n_angle, axis=2), axes=2)  # (R, D, A)
    return np.ascontiguousarray(x.transpose(0, 2, 1))


def axis_kernels(profile: RadarProfile, scat: Scatterers, *, tdm_coupling: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    elements = cc.window_array * _element_phasors(profile, f_doppler, sin_t, tdm_coupling)  # (P, K)
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
