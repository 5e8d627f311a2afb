"""TI mmWave .cfg -> radar profile: parsing, TI's derived figures, the TDM order, calibration, refusals."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from pipelines.cli import main
from radar.errors import UserError
from radar.profiles import get_profile
from radar.profiles.files import profile_from_dict
from radar.ti.cfg import load_cfg, parse_cfg
from radar.ti.convert import profile_table, ti_figures

ROOT = Path(__file__).resolve().parents[3]
AWR1843 = ROOT / "docs" / "profiles" / "awr1843_indoor.cfg"
THREE_TX = Path(__file__).with_name("configs") / "xwr1443_three_tx_real.cfg"


def _profile(cfg, **options):
    return profile_from_dict(profile_table(cfg, name="t", **options), source="test")


def test_awr1843_cfg_reads_as_ti_states_it():
    cfg = load_cfg(AWR1843)
    assert cfg.rx_channels == (0, 1, 2, 3) and cfg.tx_fired == (0, 2)
    assert (cfg.adc_bits, cfg.adc_format, cfg.loops, cfg.frame_period_ms) == (16, "complex 1x", 128, 50.0)
    p = cfg.profile
    assert (p.start_freq_ghz, p.idle_time_us, p.adc_start_time_us, p.ramp_end_time_us, p.slope_mhz_per_us,
            p.samples, p.sample_rate_ksps) == (77, 30, 6, 62, 60, 128, 2500)
    assert "cfarCfg" in cfg.ignored and "guiMonitor" in cfg.ignored and cfg.unknown == ()


def test_profile_reproduces_tis_figures():
    """Range resolution c fs / (2 S N), max range c fs / (2 S), velocity resolution c / (2 f0 Tc loops n_tx): the
    profile's (c = 299792458) within 0.1 % of TI's (c = 3e8), and the chirp cycle n_tx (idle + ramp end) exact."""
    for path in (AWR1843, THREE_TX):
        cfg = load_cfg(path)
        profile, figures = _profile(cfg), ti_figures(cfg)
        real = 2 if cfg.real_adc else 1
        assert profile.range_resolution == pytest.approx(figures["range_resolution_m"], rel=1e-3)
        assert profile.max_range / real == pytest.approx(figures["max_range_m"], rel=1e-3)
        assert profile.velocity_resolution == pytest.approx(figures["velocity_resolution_mps"], rel=1e-3)
        assert profile.max_velocity == pytest.approx(figures["max_velocity_mps"], rel=1e-3)
        p = cfg.profile
        assert profile.chirp.chirp_cycle_s == pytest.approx(len(cfg.tx_fired) * (p.idle_time_us + p.ramp_end_time_us)
                                                            * 1e-6, rel=1e-12)
        assert profile.sampled_bandwidth_hz == pytest.approx(p.slope_mhz_per_us * 1e12 * p.samples
                                                             / (p.sample_rate_ksps * 1e3), rel=1e-9)
    assert ti_figures(load_cfg(AWR1843))["range_resolution_m"] == pytest.approx(0.048828125)


def test_three_tx_order_real_adc_legacy_adcbuf_and_board_positions():
    cfg = load_cfg(THREE_TX)
    assert cfg.tx_fired == (0, 2, 1) and cfg.real_adc and cfg.adc_bits == 14
    assert cfg.unknown == ("myVendorCommand",)
    profile = _profile(cfg, board="IWR1843BOOST")
    assert profile.chirp.tdm_order == (0, 2, 1) and profile.chirp.real_adc
    # element k = tx * 4 + rx, tx numbering TX0, TX1, TX2: TX1 is elevated at azimuth 2
    assert [p[0] for p in profile.antenna_positions] == [0, 1, 2, 3, 2, 3, 4, 5, 4, 5, 6, 7]
    assert [p[1] for p in profile.antenna_positions] == [0] * 4 + [1] * 4 + [0] * 4
    assert dict(profile.capture)["adc_bits"] == 14


def test_calibration_follows_the_firing_order():
    """The SDK's pairs are by firing slot (TX0, TX2, TX1 here), stored per element tx * n_rx + rx (TX0, TX1, TX2)."""
    cal = _profile(load_cfg(THREE_TX)).calibration
    assert cal.range_bias_m == 0.07
    assert cal.coefficients == (1, 1j, -1, -1j, 0.5, 0.5j, -0.5, -0.5j, 2, 2j, -2, -2j)


BASE = AWR1843.read_text()


@pytest.mark.parametrize("edit, named", [
    (("bpmCfg -1 0 0 1", "bpmCfg -1 1 0 1"), "bpmCfg"),
    (("dfeDataOutputMode 1", "dfeDataOutputMode 3"), "dfeDataOutputMode"),
    (("sensorStart", "advFrameCfg 1 0 0 1 0"), "advFrameCfg"),
    (("sensorStart", "subFrameCfg 0 0 0 1 1 100 0 1 1 100"), "subFrameCfg"),
    (("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 1 1 1 0 0 0 0 4\nprofileCfg 1 77 30 6 62 0 0 60 1 128 2500 0 0 30"),
     "one profile only"),
    (("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 1 1 0 0 0 0 0 5"), "chirpCfg"),
    (("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 1 1 0 0 0 0 0 1"), "fires twice"),
    (("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 1 1 0 0 0 0 0 2"), "does not enable"),
    (("channelCfg 15 5 0", "channelCfg 15 5 1"), "channelCfg"),
    (("adcbufCfg -1 0 1 1 1", "adcbufCfg -1 1 1 1 1"), "adcbufCfg"),
    (("frameCfg 0 1 128 0 50 1 0", "frameCfg 0 1 128 0 50 1"), "frameCfg takes 7 arguments, got 6"),
    (("frameCfg 0 1 128 0 50 1 0", ""), "no frameCfg"),
    (("profileCfg 0 77 30 6 62", "profileCfg 0 77 30 40 62"), "ADC window"),
    (("chirpCfg 0 0 0 0 0 0 0 1", "chirpCfg 0 0 0 0 0.5 0 0 1"), "per-chirp variations"),
])
def test_what_a_profile_cannot_represent_is_refused_naming_the_command(edit, named):
    old, new = edit
    assert old in BASE
    with pytest.raises(UserError, match=named) as info:
        cfg = parse_cfg(BASE.replace(old, new), "awr.cfg")
        _profile(cfg)  # the ADC window is checked when the profile is built
    assert "\n" not in str(info.value)


def test_a_misspelled_command_is_named_as_unknown_with_the_command_it_misspells():
    assert "profileCfg 0 77" in BASE
    with pytest.raises(UserError) as info:
        parse_cfg(BASE.replace("profileCfg 0 77", "profileCgf 0 77"), "awr.cfg")
    message = str(info.value)
    assert "no profileCfg defines" in message  # the failure itself, then its likely cause
    assert "unknown command(s): awr.cfg:" in message and "profileCgf (did you mean profileCfg?)" in message
    with pytest.raises(UserError) as info:  # a stranger with no near namesake is named, without a guess
        parse_cfg(BASE.replace("profileCfg 0 77", "vendorThing 0 77"), "awr.cfg")
    assert "vendorThing" in str(info.value) and "did you mean" not in str(info.value)


def test_from_ti_then_show(tmp_path, capsys):
    out = tmp_path / "awr.toml"
    assert main(["radar", "from-ti", str(AWR1843), "--out", str(out), "--board", "awr1843boost",
                 "--angle-bins", "32"]) == 0
    printed = capsys.readouterr().out
    assert "TI's figures" in printed and "ignored" in printed
    profile = get_profile(str(out))
    assert profile.shape == (128, 32, 128) and profile.chirp.idle_time_s == 30e-6
    assert main(["radar", "show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "TI timing" in shown and "ramp end 62 us" in shown
    assert main(["radar", "from-ti", str(tmp_path / "missing.cfg"), "--out", str(out)]) == 2


def test_from_ti_gives_a_short_range_radar_rooms_at_its_scale(tmp_path, capsys):
    """A 6 m radar's profile simulates people walking in a room, not cars and cyclists at road speeds."""
    out = tmp_path / "awr.toml"
    assert main(["radar", "from-ti", str(AWR1843), "--out", str(out), "--board", "xwr1843boost"]) == 0
    assert "scene: rooms at the radar's scale" in capsys.readouterr().out
    profile = get_profile(str(out))
    scene = profile.extra["scene"]
    assert 0 < scene.range_m[0] < scene.range_m[1] < profile.max_range < 7
    assert dict(scene.classes) == {"pedestrian": (1, 3)}  # no cyclist, no car
    assert scene.speed_range("pedestrian")[1] <= min(1.4, profile.max_velocity)
    assert main(["radar", "from-ti", str(AWR1843), "--out", str(out), "--no-scene"]) == 0
    assert get_profile(str(out)).extra.get("scene") is None


def test_a_long_range_radar_keeps_the_road_scenes():
    from radar.profiles.scene_settings import default_scene

    assert default_scene(get_profile("small")) is None  # sees 50 m: the road radars' scenes suit it


def test_hand_written_timing_must_agree(tmp_path):
    table = profile_table(load_cfg(AWR1843), name="t")
    table["chirp"]["chirp_cycle_s"] = 1e-4  # not 2 x (30 + 62) us
    with pytest.raises(ValueError, match="chirp_cycle_s"):
        profile_from_dict(table)
    table["chirp"]["chirp_cycle_s"] = 184e-6
    assert math.isclose(profile_from_dict(table).chirp.chirp_cycle_s, 184e-6)
