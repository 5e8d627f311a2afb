"""An uncalibrated radar's channel mismatch in the simulator (radar/simulate/channels.py): stated in a profile's
``[simulation]`` table, it raises the angle sidelobes as a real board's does, enters the labels as it enters the
samples, and changes nothing for a profile that states none."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from radar.adc import adc_to_rad
from radar.profiles import get_profile
from radar.profiles.files import ProfileError, profile_from_dict, profile_to_dict
from radar.simulate import simulate_sequence
from radar.simulate.channels import draw_channel_gains
from radar.simulate.fmcw import Scatterers, received_amplitude, synthesize_adc
from radar.simulate.labels import exact_labels
from tests.radar.test_scenes import TI_PROFILE, indoor_profile


def sidelobe_floor_db(profile, gains) -> float:
    """Median angle-spectrum level 12+ bins from the peak of a static point at 5.2 m, 10 deg, relative to the peak."""
    angle = np.radians(10.0)
    point = Scatterers(np.array([5.2 * np.sin(angle)]), np.array([5.2 * np.cos(angle)]), np.zeros(1), np.zeros(1),
                       received_amplitude(profile, [5.2], [0.0]).astype(complex))
    power = np.abs(adc_to_rad(profile, synthesize_adc(profile, point, channel_gains=gains))) ** 2
    r, a, d = np.unravel_index(np.argmax(power), power.shape)
    spectrum = 10 * np.log10(power[r, :, d] / power[r, a, d])
    return float(np.median(spectrum[np.abs(np.arange(len(spectrum)) - a) >= 12]))


def test_channel_errors_raise_the_angle_sidelobes():
    ideal = get_profile(TI_PROFILE)
    assert draw_channel_gains(dataclasses.replace(ideal, channel_phase_error_deg=0.0, channel_gain_error_db=0.0),
                              np.random.default_rng(0)) is None
    floors = [sidelobe_floor_db(ideal, draw_channel_gains(ideal, np.random.default_rng(seed))) for seed in range(12)]
    perfect = sidelobe_floor_db(ideal, None)
    assert ideal.channel_phase_error_deg == 8.0  # the recorded board's, from its static reflector
    assert perfect < -40  # the Hann window's sidelobes alone
    assert -30 < np.median(floors) < -20  # the recorded frame's reflector: -25 dB


def test_the_drawn_errors_have_the_stated_spread():
    profile = dataclasses.replace(get_profile(TI_PROFILE), channel_phase_error_deg=10.0, channel_gain_error_db=2.0)
    gains = np.array([draw_channel_gains(profile, np.random.default_rng(seed)) for seed in range(400)])
    assert gains.shape == (400, 8)
    assert np.degrees(np.angle(gains)).std() == pytest.approx(10.0, rel=0.1)
    assert (20 * np.log10(np.abs(gains))).std() == pytest.approx(2.0, rel=0.1)


def test_labels_follow_the_channels_the_samples_were_made_with():
    profile = get_profile(TI_PROFILE)
    gains = draw_channel_gains(profile, np.random.default_rng(3))
    walker = Scatterers(np.array([0.4]), np.array([3.0]), np.zeros(1), np.array([0.6]),
                        received_amplitude(profile, [3.0], [-5.0]).astype(complex))
    labels, _ = exact_labels(profile, [walker], [1], channel_gains=gains)
    power = 10 * np.log10(np.abs(adc_to_rad(profile, synthesize_adc(profile, walker, channel_gains=gains))) ** 2 + 1)
    labelled = power[labels == 1]
    assert labelled.size and labelled.min() >= power.max() - 20 - 0.5  # within 20 dB of the peak, as the rule says


def test_the_profile_file_states_and_keeps_them():
    profile = indoor_profile()
    assert (profile.channel_phase_error_deg, profile.channel_gain_error_db) == (8.0, 1.0)
    again = profile_from_dict(profile_to_dict(profile), source="stored")
    assert (again.channel_phase_error_deg, again.channel_gain_error_db) == (8.0, 1.0)
    data = profile_to_dict(profile)
    data["simulation"]["channel_phase_error_deg"] = 400
    with pytest.raises(ProfileError, match="channel_phase_error_deg = 400, expected a standard deviation"):
        profile_from_dict(data, source="bad")


def test_the_errors_change_the_cubes_not_the_radar():
    profile = indoor_profile()
    ideal = dataclasses.replace(profile, channel_phase_error_deg=0.0, channel_gain_error_db=0.0)
    assert profile.fingerprint == ideal.fingerprint  # simulation settings, not the radar's bins
    a = next(simulate_sequence(profile, 1, seed=4))
    b = next(simulate_sequence(ideal, 1, seed=4))
    assert not np.allclose(a.cube, b.cube)
    assert "channel_phase_error_deg" not in profile_to_dict(ideal)["simulation"]  # files without them stay as they were
