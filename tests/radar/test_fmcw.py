import numpy as np
import pytest

from radar.adc import adc_to_rad
from radar.profiles import PRESETS, get_profile
from radar.simulate import point_target_cube
from radar.simulate.fmcw import Scatterers, axis_kernels, received_amplitude, synthesize_adc

N_POSITIONS = {"small": 24, "carrada": 10, "nxp": 4}


def _circular_error(found, expected, size):
    err = abs(found - expected) % size
    return min(err, size - err)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_point_targets_land_in_the_expected_bins(name):
    p = get_profile(name)
    rng = np.random.default_rng(42)
    for i in range(N_POSITIONS[name]):
        rng_m = rng.uniform(3.0, 0.85 * p.max_range)
        sign = 1 if i % 2 else -1  # both signs of angle and velocity, alternating
        angle = sign * rng.uniform(0.0, 60.0)
        velocity = -sign * rng.uniform(0.0, 0.9 * p.max_velocity)
        cube = point_target_cube(name, rng_m, angle, velocity, rcs_dbsm=20.0, noise=True, seed=i)
        assert cube.shape == p.shape and cube.dtype == np.complex64
        r, a, d = np.unravel_index(np.argmax(np.abs(cube)), cube.shape)
        assert abs(r - p.range_bin(rng_m)) <= 1.0, (rng_m, r)
        assert abs(a - p.angle_bin(angle)) <= 1.0, (angle, a)
        assert _circular_error(d, p.doppler_bin(velocity), p.n_doppler) <= 1.0, (velocity, d)


@pytest.mark.parametrize("name", ["small", "carrada"])
def test_received_power_falls_as_r_to_the_fourth(name):
    p = get_profile(name)
    ranges = np.array([5.0, 10.0, 20.0, 30.0, 45.0])
    energy = []
    for rng_m in ranges:
        cube = point_target_cube(name, rng_m, 10.0, 2.0, rcs_dbsm=10.0, noise=False)
        # Energy around the peak does not depend on where the target falls inside a bin.
        r0 = int(round(p.range_bin(rng_m)))
        energy.append((np.abs(cube[max(r0 - 6, 0):r0 + 7]) ** 2).sum())
    measured_db = 10 * np.log10(np.array(energy) / energy[0])
    expected_db = -40 * np.log10(ranges / ranges[0])
    np.testing.assert_allclose(measured_db, expected_db, atol=1.0)


def test_noise_floor_and_snr_match_the_profile_calibration():
    p = get_profile("small")
    noise_only = point_target_cube(p, 20.0, 0.0, 0.0, rcs_dbsm=-200.0, noise=True, seed=3)
    assert 10 * np.log10(np.mean(np.abs(noise_only) ** 2)) == pytest.approx(p.noise_floor_db, abs=0.2)
    # 0 dBsm at 10 m on bin centres: peak SNR equals the profile's calibration constant.
    clean = point_target_cube(p, p.range_m(round(p.range_bin(10.0))), 0.0, 0.0, rcs_dbsm=0.0, noise=False)
    snr = 10 * np.log10(np.abs(clean).max() ** 2) - p.noise_floor_db
    expected = p.snr_0dbsm_10m_db + 40 * np.log10(10.0 / p.range_m(round(p.range_bin(10.0))))
    assert snr == pytest.approx(expected, abs=0.05)


def test_axis_kernels_reproduce_the_fft_chain_exactly():
    p = get_profile("small")
    rng = np.random.default_rng(1)
    n = 7
    scat = Scatterers(rng.uniform(-10, 10, n), rng.uniform(3, 40, n), rng.normal(0, 3, n), rng.normal(0, 3, n),
                      received_amplitude(p, 20.0, rng.uniform(-5, 15, n)) * np.exp(2j * np.pi * rng.random(n)))
    for tdm in (False, True):
        chain = adc_to_rad(p, synthesize_adc(p, scat, tdm_coupling=tdm))
        kr, ka, kd = axis_kernels(p, scat, tdm_coupling=tdm)
        direct = np.einsum("pr,pa,pd->rad", kr * scat.amplitude[:, None], ka, kd)
        assert np.abs(chain - direct).max() <= 1e-5 * np.abs(direct).max()


def test_tdm_coupling_shifts_a_moving_target_in_angle_only():
    p = get_profile("carrada")
    scat = Scatterers(np.array([0.0]), np.array([20.0]), np.array([0.0]), np.array([8.0]),
                      np.array([received_amplitude(p, 20.0, 10.0) + 0j]))
    plain = np.abs(adc_to_rad(p, synthesize_adc(p, scat)))
    coupled = np.abs(adc_to_rad(p, synthesize_adc(p, scat, tdm_coupling=True)))
    peak_plain = np.unravel_index(plain.argmax(), plain.shape)
    peak_coupled = np.unravel_index(coupled.argmax(), coupled.shape)
    assert peak_plain[0] == peak_coupled[0] and peak_plain[2] == peak_coupled[2]
    assert peak_plain[1] != peak_coupled[1]


def test_adc_to_rad_rejects_a_wrong_block_shape():
    with pytest.raises(ValueError, match="shape"):
        adc_to_rad(get_profile("small"), np.zeros((10, 10, 10), np.complex64))
