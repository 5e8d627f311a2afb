"""ADC -> RAD processing: the open chain from raw complex ADC samples to a RAD cube in the project's
frame, the same code the simulator uses (:func:`adc_to_rad`).

Layouts of the raw samples of one frame (complex):

- ``"sck"``: (samples, chirp cycles, virtual elements) = (Ns, Nc, K), virtual element
  ``k = tx * n_rx + rx``; what :func:`radar.simulate.fmcw.synthesize_adc` produces.
- ``"ti"``: TI mmWave's TX-interleaved chirps as (chirps, rx, samples) = (Nc * n_tx, n_rx, Ns): chirp
  ``m * n_tx + j`` is cycle ``m``'s ``j``-th chirp, fired by TX ``tdm_order[j]`` (DCA1000 captures
  reshaped to complex (chirp, rx, sample)).

Chain: window and range FFT (zero-padded), window and Doppler FFT (zero-padded, fftshifted), TDM
Doppler-angle compensation (a TX firing later in the cycle sees the target moved further), window
and angle FFT zero-padded to the profile's angle bins (fftshifted).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft

from radar.adc_checks import check_adc
from radar.profiles import RadarProfile

LAYOUTS = ("sck", "ti")
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


def element_azimuths(profile: RadarProfile) -> np.ndarray:
    """(K,) azimuth of each virtual element in half wavelengths: the profile's stated positions, else 0 .. K-1."""
    if profile.antenna_positions:
        return np.array([azimuth for azimuth, _ in profile.antenna_positions], dtype=np.float64)
    return np.arange(profile.n_virtual, dtype=np.float64)


def _uniform_line(profile: RadarProfile) -> bool:
    return np.array_equal(element_azimuths(profile), np.arange(profile.n_virtual))


@lru_cache(maxsize=16)
def chain_constants(profile: RadarProfile) -> ChainConstants:
    w_r, w_d, w_a = (window(profile, n) for n in (profile.n_samples, profile.n_chirps, profile.n_virtual))
    a = np.arange(profile.n_angle)[:, None] - profile.n_angle // 2
    k = element_azimuths(profile)[None, :]  # elements at their azimuth (several may share one: elevated TX)
    angle_dft = (np.exp(-2j * np.pi * a * k / profile.n_angle) * w_a[None, :]).astype(np.complex64)
    noise_gain = float((w_r**2).sum() * (w_d**2).sum() * (w_a**2).sum())
    peak_gain = float((w_r.sum() * w_d.sum() * w_a.sum()) ** 2)
    noise_voxel = 10 ** (profile.noise_floor_db / 10)
    adc_noise_std = float(np.sqrt(noise_voxel / noise_gain))
    # SNR of a 0 dBsm target at 10 m: G^2 / 10^4 * peak_gain / noise_voxel = 10^(snr/10)
    radar_constant = float(np.sqrt(10 ** (profile.snr_0dbsm_10m_db / 10) * noise_voxel * 1e4 / peak_gain))
    return ChainConstants(w_r, w_d, w_a, angle_dft, noise_gain, peak_gain, adc_noise_std, radar_constant)


def tdm_slots(profile: RadarProfile) -> np.ndarray:
    """(K,) firing slot within a chirp cycle of each virtual element's TX (element k = tx * n_rx + rx)."""
    order = tuple(range(profile.n_tx)) if profile.chirp is None else profile.chirp.tdm_order
    slot_of_tx = np.argsort(np.asarray(order))
    return slot_of_tx[np.arange(profile.n_virtual) // profile.n_rx]


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
    if profile.n_virtual <= SMALL_ARRAY or not _uniform_line(profile):
        # (A, K) @ (R, K, D) -> (R, A, D): window, zero-padding and fftshift are in the DFT matrix.
        return np.matmul(cc.angle_dft, x.transpose(0, 2, 1))
    x = x * cc.window_array[None, None, :].astype(np.float32)
    x = scipy.fft.fftshift(scipy.fft.fft(x, n=profile.n_angle, axis=2), axes=2)  # (R, D, A)
    return np.ascontiguousarray(x.transpose(0, 2, 1))


def adc_shape(profile: RadarProfile, layout: str = "sck") -> tuple[int, int, int]:
    if layout == "sck":
        return (profile.n_samples, profile.n_chirps, profile.n_virtual)
    if layout == "ti":
        return (profile.n_chirps * profile.n_tx, profile.n_rx, profile.n_samples)
    raise ValueError(f"unknown ADC layout {layout!r}; expected one of {list(LAYOUTS)}")


def ti_to_sck(raw: np.ndarray, profile: RadarProfile) -> np.ndarray:
    """TX-interleaved (Nc * n_tx, n_rx, Ns) -> (Ns, Nc, K) with k = tx * n_rx + rx."""
    order = tuple(range(profile.n_tx)) if profile.chirp is None else profile.chirp.tdm_order
    by_slot = raw.reshape(profile.n_chirps, profile.n_tx, profile.n_rx, profile.n_samples)
    by_tx = np.empty_like(by_slot)
    by_tx[:, list(order)] = by_slot  # slot j was fired by TX order[j]
    sck = by_tx.reshape(profile.n_chirps, profile.n_virtual, profile.n_samples).transpose(2, 0, 1)
    return np.ascontiguousarray(sck)


def sck_to_ti(adc: np.ndarray, profile: RadarProfile) -> np.ndarray:
    """Inverse of :func:`ti_to_sck` (to write TI-layout test data)."""
    order = tuple(range(profile.n_tx)) if profile.chirp is None else profile.chirp.tdm_order
    by_tx = adc.transpose(1, 2, 0).reshape(profile.n_chirps, profile.n_tx, profile.n_rx, profile.n_samples)
    return np.ascontiguousarray(by_tx[:, list(order)].reshape(-1, profile.n_rx, profile.n_samples))


def layout_hint(shape: tuple[int, ...], profile: RadarProfile, layout: str) -> str:
    """``"; that is the shape of layout 'ti'"`` when ``shape`` fits another layout of ``profile``, else ``""``."""
    others = [other for other in LAYOUTS if other != layout and adc_shape(profile, other) == tuple(shape)]
    return f"; that is the shape of layout {others[0]!r}" if others else ""


def process_adc(adc: np.ndarray, profile: RadarProfile, *, layout: str = "sck",
                tdm_compensation: bool = True) -> np.ndarray:
    """Raw complex ADC samples of one frame -> (R, A, D) complex64 RAD cube.

    ``tdm_compensation`` says whether the samples carry TDM Doppler-angle coupling to remove: they do when
    a real TDM-MIMO radar recorded them, and when the simulator wrote them (``SimulatorConfig.tdm_coupling``,
    on by default; a recording says so in ``recording.json``), so the default processes the simulator's own
    ADC into the simulator's own cube. Pass ``False`` for ADC without coupling.
    """
    expected = adc_shape(profile, layout)
    if adc.shape != expected:
        raise ValueError(f"ADC samples for profile {profile.name!r} in layout {layout!r} must have shape "
                         f"{expected}, got {adc.shape}{layout_hint(adc.shape, profile, layout)}")
    if not np.iscomplexobj(adc):
        raise ValueError(f"ADC samples must be complex (I/Q), got dtype {adc.dtype}")
    if not np.isfinite(adc).all():
        raise ValueError("ADC samples contain NaN or Inf")
    check_adc(adc, channel_axis=1 if layout == "ti" else 2)  # undecoded words refused, DC and clipping warned
    sck = ti_to_sck(adc, profile) if layout == "ti" else adc
    if profile.calibration is not None:  # per-channel phase and gain (the profile's [calibration]); range bias is not
        sck = sck * np.asarray(profile.calibration.coefficients, np.complex64)[None, None, :]  # applied to bins
    return adc_to_rad(profile, sck.astype(np.complex64, copy=False), tdm_compensation=tdm_compensation)
