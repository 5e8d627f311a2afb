"""?input=adc takes one frame of the model's radar as it comes off a TI radar: int16 with I/Q on a trailing axis of 2
or complex, in the "ti" (chirps, rx, samples) or "sck" (samples, chirps, virtual elements) layout (?layout=, or by
shape), or a DCA1000 capture (?format=dca1000&frame=K) read with the model's radar profile. Every form of the same
frame gets the same answer; what does not fit is refused with one line (422/413), never a 500."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from radar.adc import sck_to_ti
from radar.ti.capture_writer import write_dca1000
from radar.ti.dca1000 import CaptureFormat
from service.encoding import decode_array
from service.settings import ModelSpec, Settings
from tests.service.conftest import NPY, npy_bytes
from tests.service.openradar_model import (
    as_complex,
    openradar_profile,
    save_openradar_checkpoints,
    sck_frame,
    ti_frame_iq,
    undecoded_words,
)

pytestmark = pytest.mark.slow  # a model of the recorded radar segments about 1 s of CPU a request

OCTETS = {"content-type": "application/octet-stream"}
SEGMENT = "/v1/segment?input=adc&outputs=objects,masks"
LIMIT = 9 * 2**20  # the radar's complex64 cube (8 MiB) fits, and 18 frames of capture (512 KiB each)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from service.main import create_app

    root = tmp_path_factory.mktemp("openradar")
    det, seg = save_openradar_checkpoints(root)
    settings = Settings(models=[ModelSpec(name="openradar", detector=det, segmenter=seg, score_threshold=0.0,
                                          max_objects=1)],
                        data_dir=root / "data", warmup=False, max_body_bytes=LIMIT)
    with TestClient(create_app(settings)) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    """Three whole-number frames in the "ti" layout: the recorded one, its chirps rolled, its samples reversed (its
    ranges mirrored: unlike the first)."""
    ti = as_complex(ti_frame_iq())
    return [ti, np.roll(ti, 2, axis=0), ti[..., ::-1].copy()]


@pytest.fixture(scope="module")
def capture(tmp_path_factory, frames) -> bytes:
    path = tmp_path_factory.mktemp("capture") / "adc_data.bin"
    write_dca1000(path, frames, CaptureFormat.of_profile(openradar_profile()))
    return path.read_bytes()


def masks(answer) -> tuple[np.ndarray, np.ndarray]:
    assert answer.status_code == 200, answer.text
    body = answer.json()
    return decode_array(body["ra_mask"]), decode_array(body["rd_mask"])


def test_every_form_of_the_recorded_frame_gets_the_same_answer(client):
    reference = client.post(SEGMENT, content=npy_bytes(sck_frame()), headers=NPY)
    expected = masks(reference)
    assert reference.json()["objects"], "the model found nothing: the masks would compare empty"
    forms = {
        "int16 I/Q, ti by shape": (SEGMENT, ti_frame_iq()),
        "int16 I/Q, ?layout=ti": (SEGMENT + "&layout=ti", ti_frame_iq()),
        "complex128, ti": (SEGMENT, as_complex(ti_frame_iq()).astype(np.complex128)),
        "int16 I/Q, sck, big-endian": (SEGMENT + "&layout=sck", np.stack(
            [sck_frame().real, sck_frame().imag], axis=-1).astype(">i2")),
    }
    for what, (url, array) in forms.items():
        got = masks(client.post(url, content=npy_bytes(array), headers=NPY))
        assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True)), what


def test_a_frame_that_fits_no_layout_or_the_wrong_one_is_refused_in_one_line(client):
    wrong_layout = client.post(SEGMENT + "&layout=sck", content=npy_bytes(ti_frame_iq()), headers=NPY)
    assert wrong_layout.status_code == 422, wrong_layout.text
    detail = wrong_layout.json()["detail"]
    assert "(256, 4, 128, 2)" in detail and "(128, 128, 8) 'sck'" in detail and "'ti'" not in detail
    float_iq = client.post(SEGMENT, content=npy_bytes(ti_frame_iq().astype(np.float32)), headers=NPY)
    assert float_iq.status_code == 422 and "int16 with I and Q on a trailing axis of 2" in float_iq.json()["detail"]
    not_adc = client.post("/v1/segment?layout=ti", content=npy_bytes(ti_frame_iq()), headers=NPY)
    assert not_adc.status_code == 422 and "?input=adc" in not_adc.json()["detail"]


@pytest.mark.parametrize("words", ["complex128", "uint16 I/Q"])
def test_undecoded_words_are_refused_with_the_decoding(client, words):
    array = undecoded_words() if words == "complex128" else ti_frame_iq().view(np.uint16)
    refused = client.post(SEGMENT, content=npy_bytes(array), headers=NPY)
    assert refused.status_code == 422, refused.text
    assert "((x + 32768) % 65536) - 32768" in refused.json()["detail"]


def test_a_capture_frame_gets_the_answer_of_the_same_frame_sent_as_npy(client, frames, capture):
    for index in (0, 2):
        taken = client.post(f"{SEGMENT}&format=dca1000&frame={index}", content=capture, headers=OCTETS)
        assert (taken.headers["X-Capture-Frames"], taken.headers["X-Capture-Frame"]) == ("3", str(index))
        alone = client.post(SEGMENT, content=npy_bytes(frames[index]), headers=NPY)
        assert all(np.array_equal(a, b) for a, b in zip(masks(taken), masks(alone), strict=True)), index
    first = client.post(f"{SEGMENT}&format=dca1000", content=capture, headers=OCTETS)  # no ?frame=: the first
    assert all(np.array_equal(a, b) for a, b in zip(masks(first), masks(client.post(
        SEGMENT, content=npy_bytes(frames[0]), headers=NPY)), strict=True))
    assert not np.array_equal(masks(first)[1], masks(client.post(
        SEGMENT, content=npy_bytes(frames[2]), headers=NPY))[1]), "frames 0 and 2 look alike: the test shows nothing"


def test_a_capture_that_does_not_fit_the_radar_is_refused_in_one_line(client, capture):
    url = f"{SEGMENT}&format=dca1000"
    cut = client.post(url, content=capture[:-1000], headers=OCTETS)
    assert cut.status_code == 422 and cut.json()["error"] == "invalid_capture", cut.text
    assert "2 whole frames and 523288 bytes of a partial last frame" in cut.json()["detail"]
    short = client.post(url, content=capture[:1000], headers=OCTETS)
    assert short.status_code == 422 and "less than one frame" in short.json()["detail"]
    past = client.post(url + "&frame=3", content=capture, headers=OCTETS)
    assert past.status_code == 422 and "frame 3 out of range: the capture holds 3 whole frames" in past.json()["detail"]
    not_adc = client.post("/v1/segment?format=dca1000", content=capture, headers=OCTETS)
    assert not_adc.status_code == 422 and "?input=adc" in not_adc.json()["detail"]
    for layout in ("sck", "ti"):  # a capture's layout is the radar's: a layout asked for is refused, not ignored
        laid = client.post(f"{url}&layout={layout}", content=capture, headers=OCTETS)
        assert laid.status_code == 422 and "?layout=" in laid.json()["detail"], laid.text


def test_a_capture_over_the_body_limit_is_refused(client, capture):
    frame_bytes = len(capture) // 3
    over = capture * 7  # 21 frames: the body limit holds 18
    declared = client.post(f"{SEGMENT}&format=dca1000", content=over, headers=OCTETS)
    assert declared.status_code == 413, declared.text
    chunked = client.post(f"{SEGMENT}&format=dca1000", headers=OCTETS,
                          content=(over[i:i + frame_bytes] for i in range(0, len(over), frame_bytes)))
    assert chunked.status_code == 413 and str(LIMIT) in chunked.json()["detail"], chunked.text


def test_sck_to_ti_is_the_layout_the_fixture_reshapes_to():
    """The helper's reshape of OpenRadar's (loops, virtual antennas, samples) is the chain's "ti" layout."""
    profile = openradar_profile()
    assert np.array_equal(sck_to_ti(sck_frame(), profile), as_complex(ti_frame_iq()))


def test_an_offset_binary_capture_is_refused_naming_it_not_billed_as_clipped(client, frames, tmp_path):
    """A DCA1000 capture of offset-binary words, read with the profile's two's complement: 422 naming offset binary
    (it was 200, a clipping warning and 8 objects where the frame has 4)."""
    path = tmp_path / "adc_data.bin"
    write_dca1000(path, frames, CaptureFormat.of_profile(openradar_profile(), offset_binary=True))
    refused = client.post(f"{SEGMENT}&format=dca1000", content=path.read_bytes(), headers=OCTETS)
    assert refused.status_code == 422, refused.text
    assert "offset-binary words read as two's complement" in refused.json()["detail"]
