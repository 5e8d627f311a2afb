"""A hostile TI .cfg: every count bounded before anything is allocated, and physical bounds on the carrier, slope,
sample rate, frame period and ADC settings, each refusal one line naming the command, the value and the bound."""

from __future__ import annotations

import re
import resource
import time
from pathlib import Path

import pytest

from pipelines.cli import main
from radar.errors import UserError
from radar.profiles.files import profile_from_dict
from radar.ti.cfg import MAX_CHIRP_INDEX, parse_cfg
from radar.ti.convert import profile_table

ROOT = Path(__file__).resolve().parents[3]
BASE = (ROOT / "docs" / "profiles" / "awr1843_indoor.cfg").read_text()


@pytest.mark.parametrize("old, new, named", [
    ("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 2 10000000 0 0 0 0 0 4", f"endIdx = 10000000 is out of bounds: a chirp "
                                                                     f"index in [2, {MAX_CHIRP_INDEX}]"),
    ("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 2 1000000000 0 0 0 0 0 4", "endIdx = 1000000000"),
    ("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 1 0 0 0 0 0 0 4", "endIdx = 0 is out of bounds: at least startIdx 1"),
    ("frameCfg 0 1 128 0 50 1 0", "frameCfg 0 100000000 128 0 50 1 0", "chirpEndIdx = 100000000"),
    ("frameCfg 0 1 128 0 50 1 0", "frameCfg 0 1 100000000 0 50 1 0", "numLoops = 100000000 is out of bounds"),
    ("frameCfg 0 1 128 0 50 1 0", "frameCfg 0 1 128 0 1e-300 1 0", "framePeriodicity = 1e-300 ms"),
    ("frameCfg 0 1 128 0 50 1 0", "frameCfg 0 1 128 0 1e300 1 0", "framePeriodicity = 1e+300 ms"),
    ("profileCfg 0 77 30", "profileCfg 0 1e-300 30", "startFreq = 1e-300 GHz is out of bounds"),
    ("0 0 60 1 128 2500", "0 0 1e-300 1 128 2500", "freqSlopeConst = 1e-300 MHz/us is out of bounds"),
    ("0 0 60 1 128 2500", "0 0 60 1 128 1e300", "digOutSampleRate = 1e+300 ksps is out of bounds"),
    ("0 0 60 1 128 2500", "0 0 60 1 100000000 2500", "numAdcSamples = 100000000 is out of bounds"),
    ("adcCfg 2 1", "adcCfg 2.5 1", "numADCBits must be a whole number, got 2.5"),
    ("adcCfg 2 1", "adcCfg 2 1.5", "adcOutputFmt must be a whole number, got 1.5"),
    ("channelCfg 15 5 0", "channelCfg 1e300 5 0", "rxChannelEn = 1e+300 is out of bounds"),
    ("channelCfg 15 5 0", "channelCfg 15 5.5 0", "txChannelEn must be a whole number"),
])
def test_hostile_counts_and_unphysical_values_are_refused_at_once(old, new, named):
    assert old in BASE
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    started = time.process_time()
    with pytest.raises(UserError, match=re.escape(named)) as info:
        cfg = parse_cfg(BASE.replace(old, new), "awr.cfg")
        profile_from_dict(profile_table(cfg, name="t"), source="t")
    assert "\n" not in str(info.value)
    assert time.process_time() - started < 1.0  # an end index of 10^7 took 23.9 s and 1.31 GB
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 50_000  # KiB


def test_from_ti_refuses_a_hostile_chirp_table_with_exit_2(tmp_path, capsys):
    cfg = tmp_path / "hostile.cfg"
    cfg.write_text(BASE.replace("chirpCfg 1 1 0 0 0 0 0 4", "chirpCfg 2 10000000 0 0 0 0 0 4"))
    assert main(["radar", "from-ti", str(cfg), "--out", str(tmp_path / "t.toml")]) == 2
    assert "endIdx = 10000000 is out of bounds" in capsys.readouterr().err


@pytest.mark.parametrize("key, value, named", [
    ("carrier_hz", "1e-300", "carrier_hz = 1e-300 is out of bounds"),
    ("carrier_hz", "1e300", "carrier_hz = 1e+300 is out of bounds"),
    ("sample_rate_hz", "1e300", "sample_rate_hz = 1e+300 is out of bounds"),
    ("chirp_cycle_s", "1e-300", "chirp_cycle_s = 1e-300 is out of bounds"),
])
def test_profile_files_have_physical_bounds(tmp_path, key, value, named):
    small = (ROOT / "radar" / "profiles" / "presets" / "small.toml").read_text()
    edited, count = re.subn(rf"(?m)^{key} = [^\s#]+", f"{key} = {value}", small)
    assert count == 1, key
    path = tmp_path / "p.toml"
    path.write_text(edited)
    from radar.profiles import get_profile

    with pytest.raises(UserError, match=re.escape(named)):
        get_profile(str(path))
