import numpy as np
import pytest

from radar.profiles import CARRADA, NXP, PRESETS, SMALL, RadarProfile, UnknownPresetError, get_profile


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_bin_physical_round_trips(name):
    p = get_profile(name)
    bins = np.linspace(0.5, p.n_range - 1, 17)
    np.testing.assert_allclose(p.range_bin(p.range_m(bins)), bins)
    angle_bins = np.linspace(1, p.n_angle - 1, 23)
    np.testing.assert_allclose(p.angle_bin(p.angle_deg(angle_bins)), angle_bins, atol=1e-9)
    np.testing.assert_allclose(p.angle_bin_from_sin(p.sin_theta(angle_bins)), angle_bins)
    doppler_bins = np.linspace(0, p.n_doppler - 1, 11)
    np.testing.assert_allclose(p.doppler_bin(p.velocity_mps(doppler_bins)), doppler_bins)
    rb, ab = p.bins_from_xy(*p.xy(bins[:5], angle_bins[:5]))
    np.testing.assert_allclose(rb, bins[:5], atol=1e-9)
    np.testing.assert_allclose(ab, angle_bins[:5], atol=1e-9)


def test_conventions_of_the_rad_frame():
    p = CARRADA
    assert p.angle_deg(p.n_angle / 2) == 0.0
    assert p.angle_deg(p.n_angle * 3 / 4) == pytest.approx(30.0)  # sin = 0.5, to the right
    assert p.velocity_mps(p.n_doppler / 2) == 0.0
    assert p.velocity_mps(p.n_doppler / 2 + 1) > 0  # receding
    x, y = p.ra_cartesian
    assert x.shape == y.shape == (256, 256)
    r, a = 100, 200
    np.testing.assert_allclose(np.hypot(x[r, a], y[r, a]), p.range_m(r), rtol=1e-6)
    assert x[r, a] > 0 and x[r, 50] < 0


def test_derived_radar_parameters():
    assert CARRADA.max_range == pytest.approx(50.0)
    assert CARRADA.max_velocity == pytest.approx(13.43, abs=0.01)
    assert CARRADA.sampled_bandwidth_hz == pytest.approx(0.767e9, rel=0.01)  # not the chip's 4 GHz
    assert NXP.range_resolution == pytest.approx(0.943, abs=0.001)
    assert NXP.velocity_resolution == pytest.approx(0.769, abs=0.001)
    assert NXP.n_samples == 212 and NXP.n_chirps == 52
    assert SMALL.shape == (128, 128, 32)
    assert SMALL.max_velocity == pytest.approx(CARRADA.max_velocity)
    assert CARRADA.num_classes == 4 and NXP.num_classes == 5


def test_profiles_reject_inconsistent_parameters():
    with pytest.raises(ValueError, match="n_range"):
        RadarProfile(name="bad", n_range=0, n_angle=8, n_doppler=8, range_res=1, velocity_res=1, n_tx=1,
                     n_rx=4, class_names=("a",))
    with pytest.raises(ValueError, match="multiples"):
        RadarProfile(name="bad", n_range=101, n_angle=8, n_doppler=8, range_res=1, velocity_res=1, n_tx=1,
                     n_rx=4, class_names=("a",), range_pad=2)
    with pytest.raises(ValueError, match="virtual array"):
        RadarProfile(name="bad", n_range=8, n_angle=4, n_doppler=8, range_res=1, velocity_res=1, n_tx=2,
                     n_rx=4, class_names=("a",))


def test_unknown_preset_names_the_choices():
    with pytest.raises(UnknownPresetError, match="carrada"):
        get_profile("radarx")
