"""The simulator's own ADC processes into the simulator's own cube on every path (library, CLI, recordings),
and a moving target keeps its angle: simulated ADC carries TDM coupling, as a real TDM-MIMO radar's does."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipelines.cli import main
from radar.adc import adc_to_rad, process_adc, sck_to_ti
from radar.io.recording import Recording
from radar.profiles import get_profile
from radar.simulate import SimulatorConfig, simulate_sequence
from radar.simulate.fmcw import Scatterers, synthesize_adc


@pytest.fixture(scope="module")
def frame():
    return next(simulate_sequence("small", 1, seed=4))


def test_simulated_adc_carries_coupling_and_processes_into_its_cube(frame):
    assert frame.extras["tdm_coupling"] and frame.extras["tdm_compensation"]
    np.testing.assert_allclose(process_adc(frame.extras["adc"], frame.profile), frame.cube, rtol=1e-5, atol=1e-3)
    # Without compensation the same samples give another cube: the coupling is really in the samples.
    uncompensated = process_adc(frame.extras["adc"], frame.profile, tdm_compensation=False)
    assert not np.allclose(uncompensated, frame.cube, rtol=1e-3, atol=1e-1)


@pytest.mark.parametrize("preset, angle_deg", [("small", 50.0), ("carrada", 5.0)])
def test_a_moving_target_keeps_its_angle_through_the_default_chain(preset, angle_deg):
    """The issue's figures: a moving target at 50 degrees came out at 43.3 (small), one at 5 at -1 (carrada)."""
    profile = get_profile(preset)
    theta = np.radians(angle_deg)
    speed = 0.4 * profile.max_velocity  # radial, receding: well inside the unaliased band
    scat = Scatterers(np.array([20 * np.sin(theta)]), np.array([20 * np.cos(theta)]),
                      np.array([speed * np.sin(theta)]), np.array([speed * np.cos(theta)]), np.array([1e4 + 0j]))
    cube = process_adc(synthesize_adc(profile, scat, tdm_coupling=True), profile)
    _, a, _ = np.unravel_index(np.abs(cube).argmax(), cube.shape)
    sin_a = (a - profile.n_angle / 2) / (profile.n_angle / 2)
    assert abs(np.degrees(np.arcsin(sin_a)) - angle_deg) < 2.0 * np.degrees(2 / profile.n_angle) / np.cos(theta)


def test_cli_and_recording_process_the_simulators_adc_into_its_cubes(tmp_path, capsys):
    out = tmp_path / "adc"
    assert main(["simulate", "--preset", "small", "--adc", "--sequences", "1", "--frames", "2", "--seed", "3",
                 "--out", str(out)]) == 0
    meta = json.loads((out / "recording.json").read_text())
    assert meta["tdm_coupling"] is True and meta["tdm_compensation"] is True
    truth = list(simulate_sequence("small", 2, seed=3))
    rec = Recording(out)
    np.testing.assert_allclose(rec.read_frame("seq_000", 1).cube, truth[1].cube, rtol=1e-5, atol=1e-2)
    rad = tmp_path / "rad.npy"
    assert main(["process-adc", str(out / "seq_000" / "adc" / "000000.npy"), "--profile", "small",
                 "--out", str(rad)]) == 0
    assert "as its recording.json says" in capsys.readouterr().out
    np.testing.assert_allclose(np.load(rad), truth[0].cube, rtol=1e-5, atol=1e-2)
    # A file outside a recording is taken as a real radar's (coupled) ADC: the same cube.
    loose = tmp_path / "frame_adc.npy"
    np.save(loose, truth[0].extras["adc"])
    assert main(["process-adc", str(loose), "--profile", "small", "--out", str(rad)]) == 0
    np.testing.assert_allclose(np.load(rad), truth[0].cube, rtol=1e-5, atol=1e-2)
    assert main(["process-adc", str(loose), "--profile", "small", "--coupling", "none", "--out", str(rad)]) == 0
    np.testing.assert_allclose(np.load(rad), adc_to_rad(truth[0].profile, truth[0].extras["adc"]),
                               rtol=1e-5, atol=1e-2)


def test_the_layout_error_names_the_layout_the_shape_matches(tmp_path, capsys, frame):
    sck = tmp_path / "sck.npy"
    np.save(sck, frame.extras["adc"])
    out = str(tmp_path / "o.npy")
    assert main(["process-adc", str(sck), "--profile", "small", "--layout", "ti", "--out", out]) == 2
    err = capsys.readouterr().err
    assert "that is the shape of layout 'sck'" in err and len(err.strip().splitlines()) == 1
    ti = tmp_path / "ti.npy"
    np.save(ti, sck_to_ti(frame.extras["adc"], frame.profile))
    assert main(["process-adc", str(ti), "--profile", "small", "--out", str(tmp_path / "o.npy")]) == 2
    assert "that is the shape of layout 'ti'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="that is the shape of layout 'ti'"):
        process_adc(sck_to_ti(frame.extras["adc"], frame.profile), frame.profile)


def test_uncoupled_simulation_is_one_switch_away_and_recorded(tmp_path):
    from pipelines.datasets.record import simulate_recording

    config = SimulatorConfig(tdm_coupling=False)
    out = simulate_recording(preset="small", sequences=1, frames=1, seed=3, out=tmp_path / "plain", progress=False,
                             adc=True, config=config)
    assert json.loads((out / "recording.json").read_text())["tdm_coupling"] is False
    truth = next(simulate_sequence("small", 1, seed=3, config=config))
    np.testing.assert_allclose(Recording(out).read_frame("seq_000", 0).cube, truth.cube, rtol=1e-5, atol=1e-2)
