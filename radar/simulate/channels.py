"""Receive and transmit channels that are not matched: the gain and phase errors of an uncalibrated radar.

A real board's TX and RX chains differ in gain and phase (TI's ``compRangeBiasAndRxChanPhase`` exists to measure and
remove them). Left in, they raise the angle spectrum's sidelobes from the window's (about -31 dB for Hann over 8
elements) to a floor set by the errors' size. A profile's ``[simulation]`` table states that size
(``channel_phase_error_deg``, ``channel_gain_error_db``: standard deviations per virtual channel); each simulated
sequence draws its own errors, as if recorded by another board of the same make. Zero (the presets): ideal channels.
"""

from __future__ import annotations

import numpy as np

from radar.profiles import RadarProfile


def draw_channel_gains(profile: RadarProfile, rng: np.random.Generator) -> np.ndarray | None:
    """(K,) complex gain of each virtual channel, K = n_tx * n_rx (element ``tx * n_rx + rx``), or None when the
    profile states no errors (no random number is drawn then). Each TX and each RX chain draws half the variance,
    so a virtual channel's phase (degrees) and gain (dB) have the stated standard deviations."""
    if not profile.has_channel_errors:
        return None

    def per_virtual_channel() -> np.ndarray:  # unit-variance error of each TX plus each RX chain, (n_tx * n_rx,)
        half = 1 / np.sqrt(2)
        return (rng.normal(0, half, profile.n_tx)[:, None] + rng.normal(0, half, profile.n_rx)[None, :]).ravel()

    phase_deg = per_virtual_channel() * profile.channel_phase_error_deg
    gain_db = per_virtual_channel() * profile.channel_gain_error_db
    return 10 ** (gain_db / 20) * np.exp(1j * np.radians(phase_deg))
