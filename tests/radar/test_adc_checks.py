"""ADC plausibility checks (radar.adc_checks) on OpenRadar's recorded frames, decoded and as the raw 16-bit words
they were published as, on each path that takes ADC: the checks themselves, process_adc, ``radarseg process-adc``,
an ADC recording read back (what ``preprocess --adc-recording`` reads) and ``segment --input adc``."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from pipelines.cli import main
from radar.adc import process_adc
from radar.adc_checks import AdcCheckError, adc_findings, check_adc
from radar.errors import DataError
from radar.frame import RadarFrame
from radar.io.recording import Recording, RecordingWriter
from radar.profiles.files import load_profile_file

ROOT = Path(__file__).resolve().parents[2]
PROFILE_PATH = ROOT / "docs" / "profiles" / "openradar_ti_2tx4rx.toml"
WORDS_HINT = "((x + 32768) % 65536) - 32768"


def decoded_ti() -> np.ndarray:
    """doppler_example_1 in the ADC chain's "ti" layout (256 chirps, 4 RX, 128 samples), decoded."""
    iq = np.load(ROOT / "tests" / "fixtures" / "openradar" / "doppler_example_1.npy")
    return (iq[..., 0] + 1j * iq[..., 1]).astype(np.complex64).reshape(256, 4, 128)


def as_raw_words(adc: np.ndarray) -> np.ndarray:
    """The frame as OpenRadar published it: each part's int16 read as an unsigned 16-bit word."""
    def word(part):
        return part.astype(np.int16).view(np.uint16).astype(np.float32)
    return (word(adc.real) + 1j * word(adc.imag)).astype(np.complex64)


@pytest.fixture(scope="module")
def profile():
    return load_profile_file(PROFILE_PATH)


def test_the_decoded_frame_passes_every_check():
    assert adc_findings(decoded_ti(), channel_axis=1) == []


def test_raw_words_are_refused_with_the_decoding_named():
    raw = as_raw_words(decoded_ti())
    assert float(raw.real.min()) >= 0 and float(raw.real.max()) > 60000  # the published form
    (finding,) = adc_findings(raw, channel_axis=1)
    assert finding.refuse and finding.check == "twos_complement_words" and WORDS_HINT in finding.message
    decoded = (((raw.real + 32768) % 65536) - 32768) + 1j * (((raw.imag + 32768) % 65536) - 32768)
    assert adc_findings(decoded, channel_axis=1) == []  # the named decoding is the fix


def test_offset_binary_words_are_refused_with_subtract_named():
    (finding,) = adc_findings(decoded_ti() + (32768 + 32768j), channel_axis=1)
    assert finding.refuse and finding.check == "offset_binary_words" and "subtract 32768" in finding.message


def test_dc_offset_warned_and_a_bare_offset_refused(caplog):
    adc = decoded_ti()
    spread = float(np.abs(adc - adc.mean()).std())
    with caplog.at_level(logging.WARNING, logger="radar.adc_checks"):
        warnings = check_adc(adc + 3 * spread, channel_axis=1)
    assert len(warnings) == 1 and "DC offset" in warnings[0] and "DC offset" in caplog.text
    with pytest.raises(AdcCheckError, match="nothing but an offset"):
        check_adc(adc + 200 * spread, channel_axis=1)


def test_clipping_warned_with_its_share():
    adc = decoded_ti() * 400  # the strongest returns pass int16 full scale
    clipped = np.clip(adc.real, -32768, 32767) + 1j * np.clip(adc.imag, -32768, 32767)
    share = np.mean(np.abs(np.stack([clipped.real, clipped.imag])) >= 32767)
    (finding,) = adc_findings(clipped, channel_axis=1)
    assert finding.check == "clipping" and not finding.refuse and f"{share:.2%}" in finding.message
    assert adc_findings(decoded_ti() * 10, channel_axis=1) == []  # loud but unclipped: nothing to say


def test_process_adc_refuses_raw_words(profile):
    with pytest.raises(AdcCheckError, match=r"raw unsigned 16-bit words"):
        process_adc(as_raw_words(decoded_ti()), profile, layout="ti")


def test_process_adc_command_refuses_raw_words_with_one_line(tmp_path, capsys):
    np.save(tmp_path / "raw.npy", as_raw_words(decoded_ti()))
    np.save(tmp_path / "decoded.npy", decoded_ti())
    args = ["--profile", str(PROFILE_PATH), "--layout", "ti"]
    assert main(["process-adc", str(tmp_path / "raw.npy"), *args, "--out", str(tmp_path / "a.npy")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and WORDS_HINT in err and not (tmp_path / "a.npy").exists()
    assert main(["process-adc", str(tmp_path / "decoded.npy"), *args, "--out", str(tmp_path / "b.npy")]) == 0
    assert np.load(tmp_path / "b.npy").shape == profile_shape()


def profile_shape():
    return load_profile_file(PROFILE_PATH).shape


def write_adc_recording(root: Path, profile, adc_sck: np.ndarray) -> Path:
    frame = RadarFrame(cube=np.zeros(profile.shape, np.complex64), profile=profile, sequence="seq_000", index=0,
                       labels=np.zeros(profile.shape, np.uint8), instances=np.zeros(profile.shape, np.uint8),
                       extras={"adc": adc_sck, "tdm_compensation": True})
    with RecordingWriter(root, profile, source={"kind": "test"}, content="adc") as writer:
        writer.write(frame)
    return root


def test_an_adc_recording_of_raw_words_is_refused_naming_the_file(tmp_path, profile):
    from radar.adc import ti_to_sck

    good = write_adc_recording(tmp_path / "good", profile, ti_to_sck(decoded_ti(), profile))
    assert Recording(good).read_frame("seq_000", 0).cube.shape == profile.shape
    bad = write_adc_recording(tmp_path / "bad", profile, ti_to_sck(as_raw_words(decoded_ti()), profile))
    assert json.loads((bad / "recording.json").read_text())["content"] == "adc"
    with pytest.raises(DataError, match=r"000000\.npy: .*raw unsigned 16-bit words"):
        Recording(bad).read_frame("seq_000", 0)


def test_segment_input_adc_refuses_raw_words(tmp_path, tiny_checkpoints, frame_small_adc):
    from pipelines.inference.segment import segment_file

    det, seg = tiny_checkpoints
    np.save(tmp_path / "raw.npy", as_raw_words(np.round(frame_small_adc)))
    with pytest.raises(DataError, match="raw unsigned 16-bit words"):
        segment_file(tmp_path / "raw.npy", detector=det, segmenter=seg, input_kind="adc", warm_up=False)


@pytest.fixture(scope="module")
def frame_small_adc():
    """A simulated frame of the small preset's ADC (samples, chirps, virtual elements), at integer scale."""
    from radar.simulate import simulate_sequence

    adc = next(simulate_sequence("small", 1, seed=2)).extras["adc"]
    return (adc / np.abs(adc).std() * 200).astype(np.complex64)
