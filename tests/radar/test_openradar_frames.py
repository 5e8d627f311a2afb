"""OpenRadar's two recorded TI frames through the project's ADC chain, against a plain-numpy chain written here.

The numpy chain finds the targets on its own (no bin is written down in this file): per-antenna range FFT, Doppler
FFT over the loops, power summed over the antennas; then TDM compensation and an angle FFT of the eight virtual
antennas at each target. The project's chain (radar.adc.process_adc, layout "ti") must put every target on the same
range and Doppler bin and within one angle bin, with the project's sign convention: positive velocity = receding
(phase growing over the chirps = range growing, for a complex IF whose range bins are positive).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from radar.adc import process_adc
from radar.profiles.files import load_profile_file
from radar.profiles.profile import SPEED_OF_LIGHT

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "tests" / "fixtures" / "openradar"
PROFILE = ROOT / "docs" / "profiles" / "openradar_ti_2tx4rx.toml"
START_HZ, SLOPE, FS, IDLE_S, RAMP_END_S = 77.4201e9, 60e12, 2.5e6, 30e-6, 62e-6  # the notebooks' radar


def complex_frame(name: str) -> np.ndarray:
    iq = np.load(FIXTURES / f"{name}.npy")
    assert iq.dtype == np.int16 and iq.shape[-1] == 2
    return iq[..., 0].astype(np.float64) + 1j * iq[..., 1]


def hann_open(n: int) -> np.ndarray:
    """Hann window without its zero end points."""
    return 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(1, n + 1) / (n + 1))


def numpy_range_doppler(frame: np.ndarray) -> np.ndarray:
    """(loops, antennas, samples) -> (loops, antennas, range) complex, Doppler fftshifted on axis 0."""
    loops, _, samples = frame.shape
    x = np.fft.fft(frame * hann_open(samples)[None, None, :], axis=2)
    return np.fft.fftshift(np.fft.fft(x * hann_open(loops)[:, None, None], axis=0), axes=0)


def strongest(power: np.ndarray, mask: np.ndarray) -> tuple[int, int]:
    """(doppler, range) of the largest ``power`` where ``mask`` holds."""
    return tuple(int(i) for i in np.unravel_index(np.argmax(np.where(mask, power, -np.inf)), power.shape))


def numpy_angle_bin(cell: np.ndarray, doppler_from_zero: int, loops: int, n_angle: int) -> int:
    """Angle bin (fftshifted, 0 at -90 deg) of the 8 virtual antennas of one range-Doppler cell: TX1 fires half a
    loop after TX0, so its antennas carry half a loop's Doppler phase more; removed before the angle FFT."""
    phase = np.ones(8, dtype=np.complex128)
    phase[4:] = np.exp(-1j * np.pi * doppler_from_zero / loops)
    spectrum = np.fft.fftshift(np.fft.fft(cell * phase * hann_open(8), n=n_angle))
    return int(np.argmax(np.abs(spectrum)))


@pytest.fixture(scope="module")
def profile():
    return load_profile_file(PROFILE)


def test_profile_matches_the_notebooks_radar(profile):
    bandwidth = SLOPE * 128 / FS
    assert profile.range_res == pytest.approx(SPEED_OF_LIGHT / (2 * bandwidth), rel=1e-9)
    cycle = 2 * (IDLE_S + RAMP_END_S)
    assert profile.velocity_res == pytest.approx(SPEED_OF_LIGHT / START_HZ / (2 * 128 * cycle), rel=1e-9)
    assert round(profile.range_res, 4) == 0.0488 and round(profile.velocity_res, 4) == 0.0822
    assert (profile.n_tx, profile.n_rx, profile.n_samples, profile.n_chirps) == (2, 4, 128, 128)


def test_doppler_example_targets_where_numpy_puts_them(profile):
    frame = complex_frame("doppler_example_1")  # (128 loops, 8 virtual, 128 samples)
    rd = numpy_range_doppler(frame)
    power = (np.abs(rd) ** 2).sum(axis=1)  # (D, R)
    zero = 64
    d_idx, r_idx = np.indices(power.shape)
    far = r_idx >= 20  # beyond 1 m: the leakage around range 0 is no target
    static = strongest(power, far & (d_idx == zero))
    receding = strongest(power, far & (d_idx >= zero + 3))
    approaching = strongest(power, far & (d_idx <= zero - 3))
    assert 5.0 < static[1] * profile.range_res < 5.4  # the scene as described: a reflector near 5.2 m
    for _, r in (receding, approaching):
        assert 2.7 < r * profile.range_res < 3.1  # and movers near 2.9 m

    rad = process_adc(frame.reshape(256, 4, 128), profile, layout="ti")  # (R, A, D)
    ours = (np.abs(rad) ** 2).sum(axis=1)  # (R, D)
    for d, r in (static, receding, approaching):
        window = ours[r - 4:r + 5, d - 4:d + 5]
        dr, dd = np.unravel_index(np.argmax(window), window.shape)
        assert (r - 4 + dr, d - 4 + dd) == (r, d), "the project's peak is off the numpy chain's bin"
        numpy_velocity = (d - zero) / 128 * SPEED_OF_LIGHT / START_HZ / (4 * (IDLE_S + RAMP_END_S))  # + = phase grows
        assert profile.velocity_mps(d) == pytest.approx(numpy_velocity, rel=1e-6)
        expected_angle = numpy_angle_bin(rd[d, :, r], d - zero, 128, profile.n_angle)
        assert abs(int(np.argmax(np.abs(rad[r, :, d]))) - expected_angle) <= 1
    assert profile.velocity_mps(receding[0]) > 0 > profile.velocity_mps(approaching[0])


def test_simple_frame_mover_where_numpy_puts_it(profile):
    frame = complex_frame("simple_frame_1")  # (128 chirps, 128 samples), one antenna
    rd = numpy_range_doppler(frame[:, None, :])[:, 0, :]
    power = np.abs(rd) ** 2
    d_idx, r_idx = np.indices(power.shape)
    mover = strongest(power, (r_idx >= 20) & (np.abs(d_idx - 64) >= 3))
    assert 1.8 < mover[1] * profile.range_res < 2.2 and mover[0] < 64  # approaching, near 2.0 m

    one_antenna = dataclasses.replace(profile, n_tx=1, n_rx=1, chirp=dataclasses.replace(profile.chirp, tdm_order=(0,)))
    rad = process_adc(frame.T[:, :, None], one_antenna, layout="sck")
    ours = (np.abs(rad) ** 2).sum(axis=1)
    masked = np.where((np.arange(128)[:, None] >= 20) & (np.abs(np.arange(128)[None, :] - 64) >= 3), ours, -np.inf)
    assert tuple(int(i) for i in np.unravel_index(np.argmax(masked), masked.shape)) == (mover[1], mover[0])
