"""ADC -> RAD processing: the open chain from raw complex ADC samples to a RAD cube in the project's
frame, with the same code the simulator uses (radar.simulate.fmcw.adc_to_rad).

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

import numpy as np

from radar.profiles import RadarProfile
from radar.simulate.fmcw import adc_to_rad

LAYOUTS = ("sck", "ti")


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


def process_adc(adc: np.ndarray, profile: RadarProfile, *, layout: str = "sck",
                tdm_compensation: bool = True) -> np.ndarray:
    """Raw complex ADC samples of one frame -> (R, A, D) complex64 RAD cube."""
    expected = adc_shape(profile, layout)
    if adc.shape != expected:
        raise ValueError(f"ADC samples for profile {profile.name!r} in layout {layout!r} must have shape "
                         f"{expected}, got {adc.shape}")
    if not np.iscomplexobj(adc):
        raise ValueError(f"ADC samples must be complex (I/Q), got dtype {adc.dtype}")
    if not np.isfinite(adc).all():
        raise ValueError("ADC samples contain NaN or Inf")
    sck = ti_to_sck(adc, profile) if layout == "ti" else adc
    return adc_to_rad(profile, sck.astype(np.complex64, copy=False), tdm_compensation=tdm_compensation)
