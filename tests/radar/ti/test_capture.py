"""DCA1000 and mmWave Studio captures: exact round trips for every layout, equality with OpenRadar's reader, one-line
refusals of truncated or mismatched files, the commands that read and write them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mmwave.dataloader import DCA1000, parse_raw_adc

from pipelines.cli import main
from radar.adc import process_adc, sck_to_ti
from radar.errors import DataError
from radar.io.recording import Recording
from radar.profiles.files import profile_from_dict
from radar.profiles.profile import ChannelCalibration
from radar.simulate import simulate_sequence
from radar.ti.capture import Capture, frames_from_bytes
from radar.ti.capture_writer import quantize, write_dca1000, write_studio_raw
from radar.ti.dca1000 import CaptureFormat

SMALL = {"name": "ti-small", "class_names": ["pedestrian"],
         "chirp": {"carrier_hz": 77e9, "slope_hz_per_s": 60e12, "sample_rate_hz": 2.5e6, "samples_per_chirp": 16,
                   "chirps_per_frame": 4, "idle_time_s": 30e-6, "ramp_end_time_s": 62e-6},
         "array": {"n_tx": 2, "n_rx": 4, "tdm_order": [1, 0]},
         "processing": {"range_pad": 1, "doppler_pad": 1, "angle_bins": 8}}
LAYOUTS = [CaptureFormat(lanes, complex_adc, order, offset)
           for lanes in (2, 4) for complex_adc in (True, False) for order in ("iq", "qi") for offset in (False, True)
           if complex_adc or order == "iq"]


def _profile(**chirp):
    return profile_from_dict({**SMALL, "chirp": {**SMALL["chirp"], **chirp}})


def _simulated_frames(profile, fmt, n=3):
    """Simulated frames in the "ti" layout, scaled and rounded into the format's words."""
    frames = [frame.extras["adc"] for frame in simulate_sequence(profile, n, seed=3)]
    scale = 2000 / max(np.abs(a).max() for a in frames)
    return [quantize(sck_to_ti(a, profile), scale, fmt)[0] for a in frames]


@pytest.mark.parametrize("fmt", LAYOUTS, ids=lambda f: f.describe().replace(" ", ""))
def test_dca1000_round_trip_is_exact(tmp_path, fmt):
    profile = _profile(adc="complex" if fmt.complex_adc else "real")
    frames = _simulated_frames(profile, fmt)
    assert any(np.abs(f.real).max() > 100 for f in frames)
    path = tmp_path / "adc_data.bin"
    assert write_dca1000(path, frames, fmt) == 3
    capture = Capture(path, profile, fmt)
    assert len(capture) == 3 and path.stat().st_size == 3 * capture.geometry.bytes
    for index, frame in enumerate(frames):
        back = capture.frame(index)
        assert back.dtype == np.complex64 and back.shape == (8, 4, 16)
        np.testing.assert_array_equal(back, frame)
    np.testing.assert_array_equal(frames_from_bytes(path.read_bytes(), profile, fmt), np.stack(frames))


def test_equal_to_openradar_on_the_same_bytes(tmp_path):
    """OpenRadar's DCA1000.organize (2 LVDS lanes, complex, I first, two's complement) reads what we read."""
    profile, fmt = _profile(), CaptureFormat()
    frames = _simulated_frames(profile, fmt)
    path = tmp_path / "adc_data.bin"
    write_dca1000(path, frames, fmt)
    raw = np.fromfile(path, dtype=np.int16)
    n = len(raw) // 3
    for index in range(3):
        theirs = DCA1000.organize(raw[index * n:(index + 1) * n], 8, 4, 16)
        np.testing.assert_array_equal(Capture(path, profile).frame(index), theirs)


def test_studio_raw_files_split_and_lost_packets(tmp_path):
    profile, fmt = _profile(), CaptureFormat()
    frames = _simulated_frames(profile, fmt)
    files = write_studio_raw(tmp_path / "adc_data", frames, fmt, payload=200, max_file_bytes=1000)
    assert len(files) > 2  # frames straddle files
    capture = Capture(files[0], profile)
    for index, frame in enumerate(frames):
        np.testing.assert_array_equal(capture.frame(index), frame)
    # OpenRadar's parse_raw_adc strips the headers of one Raw file: the same words
    whole = write_studio_raw(tmp_path / "one", frames, fmt, payload=200)
    parse_raw_adc(str(whole[0]), str(tmp_path / "clean.bin"))
    theirs = np.fromfile(tmp_path / "clean.bin", dtype=np.int16)[:1024]
    np.testing.assert_array_equal(Capture(whole[0], profile).frame(0), DCA1000.organize(theirs, 8, 4, 16))
    # a lost packet reads as zeros where it belonged, the rest in place
    lossy = Capture(write_studio_raw(tmp_path / "lossy", frames, fmt, payload=200, drop=frozenset({2}))[0], profile)
    words = lossy.words(0)
    assert np.all(words[100:200] == 0) and np.any(words[:100] != 0) and lossy.lost_bytes == 200
    np.testing.assert_array_equal(lossy.frame(1), frames[1])


def test_truncated_and_mismatched_captures_are_refused_in_one_line(tmp_path):
    profile, fmt = _profile(), CaptureFormat()
    frames = _simulated_frames(profile, fmt)
    path = tmp_path / "adc_data.bin"
    write_dca1000(path, frames, fmt)
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    with pytest.raises(DataError, match=r"2 whole frames and 1948 bytes of a partial last frame") as info:
        Capture(path, profile)
    assert "\n" not in str(info.value) and "2048 bytes a frame" in str(info.value)
    assert len(Capture(path, profile, partial="skip")) == 2
    path.write_bytes(data[:2048])  # half a complex frame of 32 samples: one real one
    with pytest.raises(DataError, match="was the ADC real"):
        Capture(path, _profile(samples_per_chirp=32))
    path.write_bytes(data[:100])
    with pytest.raises(DataError, match="holds 100 bytes, less than one frame"):
        Capture(path, profile)
    with pytest.raises(DataError, match="4 LVDS lanes carry one RX each"):
        Capture(path, profile_from_dict({**SMALL, "array": {"n_tx": 2, "n_rx": 2}}), CaptureFormat(lvds_lanes=4))


def test_calibration_multiplies_each_virtual_channel():
    profile = _profile()
    adc = np.random.default_rng(0).standard_normal((2, 16, 4, 8)).astype(np.float32)
    adc = (adc[0] + 1j * adc[1]).astype(np.complex64)
    coefficients = tuple(complex(np.cos(k), np.sin(k)) * (1 + k / 10) for k in range(8))
    calibrated = profile_from_dict({**SMALL, "chirp": SMALL["chirp"], "calibration": {
        "range_bias_m": 0.05, "channel_coefficients": [[c.real, c.imag] for c in coefficients]}})
    assert calibrated.calibration == ChannelCalibration(0.05, coefficients)
    expected = process_adc((adc * np.array(coefficients, np.complex64)).astype(np.complex64), profile)
    np.testing.assert_allclose(process_adc(adc, calibrated), expected, rtol=1e-5, atol=1e-3)


def test_process_adc_reads_a_capture_and_simulate_writes_one(tmp_path, capsys):
    profile_path = tmp_path / "small.json"
    profile_path.write_text(json.dumps({**SMALL, "capture": {"lvds_lanes": 2}}))
    rec = tmp_path / "rec"
    assert main(["simulate", "--preset", str(profile_path), "--adc", "--format", "dca1000", "--sequences", "1",
                 "--frames", "2", "--out", str(rec)]) == 0
    capture = rec / "seq_000" / "adc_data.bin"
    assert capture.stat().st_size == 2 * 8 * 4 * 16 * 2 * 2
    recording = Recording(rec)
    cube = recording.read_frame("seq_000", 1).cube
    assert main(["process-adc", str(capture), "--profile", str(profile_path), "--out", str(tmp_path / "c.npy"),
                 "--frame", "1"]) == 0
    from_capture = np.load(tmp_path / "c.npy") / recording.meta["adc_scale"]
    np.testing.assert_allclose(from_capture, cube, rtol=1e-4, atol=1e-4 * np.abs(cube).max())
    assert main(["process-adc", str(capture), "--profile", str(profile_path), "--out", str(tmp_path / "c.npy"),
                 "--frame", "2"]) == 2
    assert "frame 2 out of range" in capsys.readouterr().err
