"""Radar profiles as files, the derived quantities and every refusal, and the open ADC -> RAD chain."""

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from pipelines.cli import main
from radar.adc import adc_to_rad, process_adc, sck_to_ti, ti_to_sck
from radar.profiles import BUILTIN_PRESETS, get_profile
from radar.profiles.files import ProfileError, load_profile_file, profile_from_dict
from radar.simulate import point_target_cube
from radar.simulate.fmcw import Scatterers, received_amplitude, synthesize_adc

PRESET_DIR = Path(__file__).resolve().parents[3] / "radar" / "profiles" / "presets"

# A radar of our own: 3 TX x 4 RX TDM, 1 GHz sampled, 192 samples, 48 chirp cycles, 96 angle bins.
CUSTOM = {
    "name": "lab-radar", "class_names": ["pedestrian", "car"], "frame_rate_hz": 15.0,
    "chirp": {"carrier_hz": 77e9, "slope_hz_per_s": 50e12, "sample_rate_hz": 9.6e6, "samples_per_chirp": 192,
              "chirps_per_frame": 48, "chirp_cycle_s": 80e-6},
    "array": {"n_tx": 3, "n_rx": 4, "tdm_order": [0, 2, 1]},
    "processing": {"range_pad": 1, "doppler_pad": 2, "angle_bins": 96, "window": "hann"},
}


def _custom(**changes):
    data = json.loads(json.dumps(CUSTOM))
    for dotted, value in changes.items():
        table, _, key = dotted.rpartition(".")
        (data[table] if table else data)[key] = value
    return data


@pytest.mark.parametrize("name", BUILTIN_PRESETS)
def test_builtin_presets_are_files_whose_expectations_hold(name):
    path = PRESET_DIR / f"{name}.toml"
    profile = load_profile_file(path)
    assert profile == get_profile(name)
    expect = tomllib.loads(path.read_text())["expect"]
    assert profile.range_res == pytest.approx(expect["range_res_m"], rel=0.005)
    assert profile.velocity_res == pytest.approx(expect["velocity_res_mps"], rel=0.005)
    assert profile.max_range == pytest.approx(expect["max_range_m"], rel=0.005)


def test_a_custom_profile_derives_every_quantity(tmp_path):
    path = tmp_path / "lab.json"
    path.write_text(json.dumps(CUSTOM))
    p = get_profile(str(path))
    bandwidth = 50e12 * 192 / 9.6e6  # slope x ADC time = 1 GHz
    assert p.shape == (192, 96, 96)
    assert p.range_res == pytest.approx(299_792_458 / (2 * bandwidth))
    assert p.velocity_res == pytest.approx(299_792_458 / 77e9 / (2 * 48 * 80e-6) / 2)
    assert p.n_virtual == 12 and p.chirp.tdm_order == (0, 2, 1)
    assert p.all_class_names == ("background", "pedestrian", "car")


def test_point_targets_land_where_a_custom_profile_predicts():
    p = profile_from_dict(CUSTOM)
    rng = np.random.default_rng(0)
    for i in range(8):
        rng_m, angle = rng.uniform(3, 0.8 * p.max_range), (-1) ** i * rng.uniform(0, 50)
        velocity = (-1) ** (i // 2) * rng.uniform(0, 0.8 * p.max_velocity)
        cube = point_target_cube(p, rng_m, angle, velocity, rcs_dbsm=20.0, seed=i)
        r, a, d = np.unravel_index(np.abs(cube).argmax(), cube.shape)
        assert abs(r - p.range_bin(rng_m)) <= 1 and abs(a - p.angle_bin(angle)) <= 1
        assert abs(d - p.doppler_bin(velocity)) <= 1


def test_adc_processing_equals_the_simulators_cube_in_both_layouts():
    p = profile_from_dict(CUSTOM)
    rng = np.random.default_rng(1)
    n = 6
    scat = Scatterers(rng.uniform(-8, 8, n), rng.uniform(4, 25, n), rng.normal(0, 2, n), rng.normal(0, 2, n),
                      received_amplitude(p, 15.0, rng.uniform(0, 15, n)) + 0j)
    adc = synthesize_adc(p, scat, noise_rng=np.random.default_rng(2))
    reference = adc_to_rad(p, adc)
    np.testing.assert_array_equal(process_adc(adc, p, tdm_compensation=False), reference)
    ti = sck_to_ti(adc, p)
    assert ti.shape == (48 * 3, 4, 192)
    np.testing.assert_array_equal(ti_to_sck(ti, p), adc)
    np.testing.assert_array_equal(process_adc(ti, p, layout="ti", tdm_compensation=False), reference)
    with pytest.raises(ValueError, match="shape"):
        process_adc(adc[:10], p)
    with pytest.raises(ValueError, match="complex"):
        process_adc(adc.real.copy(), p)


def test_tdm_compensation_moves_a_fast_target_back_to_its_angle():
    p = profile_from_dict(_custom(**{"array.tdm_order": [0, 1, 2]}))
    angle = 20.0
    t = np.radians(angle)
    speed = 0.9 * p.max_velocity  # receding along the line of sight
    scat = Scatterers(np.array([15 * np.sin(t)]), np.array([15 * np.cos(t)]), np.array([speed * np.sin(t)]),
                      np.array([speed * np.cos(t)]), np.array([received_amplitude(p, 15.0, 10.0) + 0j]))
    adc = synthesize_adc(p, scat, tdm_coupling=True)
    truth = p.angle_bin(angle)
    uncompensated = process_adc(adc, p, tdm_compensation=False)
    compensated = process_adc(adc, p, tdm_compensation=True)
    a_off = np.unravel_index(np.abs(uncompensated).argmax(), uncompensated.shape)[1]
    a_on = np.unravel_index(np.abs(compensated).argmax(), compensated.shape)[1]
    assert abs(a_off - truth) > 2.5  # coupling: about 0.45 cycles x 2/3 per TX step across 4-element groups
    assert abs(a_on - truth) <= 1


@pytest.mark.parametrize("changes, message", [
    ({"chirp.colour": 1}, "unknown key"),
    ({"chirp.sweep_bandwidth_hz": 2e9}, "sweeps 1000 MHz, but sweep_bandwidth_hz says 2000 MHz"),
    ({"chirp.chirp_cycle_s": 40e-6}, "cannot fire 3 TX chirps"),
    ({"processing.angle_bins": 8}, "angle_bins"),
    ({"array.tdm_order": [0, 0, 1]}, "permutation"),
    ({"processing.window": "kaiser"}, "window"),
    ({"expect": {"range_res_m": 0.05}}, "range_res_m = 0.05, but the chirp gives 0.1499"),
    ({"chirp.samples_per_chirp": 19.5}, "integer"),
    ({"class_names": []}, "class_names"),
])
def test_inconsistent_profiles_are_refused_with_the_reason(changes, message):
    with pytest.raises(ProfileError, match=message):
        profile_from_dict(_custom(**changes))


def test_unreadable_profile_files(tmp_path):
    with pytest.raises(ProfileError, match="no such profile file"):
        load_profile_file(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed")
    with pytest.raises(ProfileError, match="not valid TOML"):
        load_profile_file(bad)
    no_chirp = tmp_path / "nochirp.json"
    no_chirp.write_text(json.dumps({k: v for k, v in CUSTOM.items() if k != "chirp"}))
    with pytest.raises(ProfileError, match=r"missing table \[chirp\]"):
        load_profile_file(no_chirp)


def test_cli_shows_profiles_and_processes_adc(tmp_path, capsys):
    profile_path = tmp_path / "lab.json"
    profile_path.write_text(json.dumps(CUSTOM))
    assert main(["radar", "show", str(profile_path)]) == 0
    assert "3 TX x 4 RX = 12 elements" in capsys.readouterr().out
    p = profile_from_dict(CUSTOM)
    adc = synthesize_adc(p, Scatterers(np.array([0.0]), np.array([10.0]), np.zeros(1), np.zeros(1),
                                       np.array([1e4 + 0j])), noise_rng=np.random.default_rng(0))
    np.save(tmp_path / "adc.npy", sck_to_ti(adc, p))
    out = tmp_path / "rad.npy"
    assert main(["process-adc", str(tmp_path / "adc.npy"), "--profile", str(profile_path), "--layout", "ti",
                 "--out", str(out)]) == 0
    np.testing.assert_allclose(np.load(out), process_adc(adc, p), rtol=1e-5, atol=1e-3)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_custom(**{"chirp.chirp_cycle_s": 1e-6})))
    assert main(["radar", "show", str(bad)]) == 2
    assert "cannot fire" in capsys.readouterr().err
