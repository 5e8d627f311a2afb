"""?input=adc on /v1/segment and on a stream: undecoded 16-bit words are refused with a 422 naming the decoding
(they used to be processed into a screen of false objects), decoded samples of the same frame are answered."""

from __future__ import annotations

import numpy as np
import pytest

from tests.service.conftest import NPY, npy_bytes

pytestmark = pytest.mark.slow  # an app with a model per test


@pytest.fixture(scope="module")
def adc_pair(frame) -> tuple[np.ndarray, np.ndarray]:
    """A simulated frame's ADC at 16-bit integer scale: decoded (signed) and as raw unsigned words."""
    adc = frame.extras["adc"]
    decoded = np.round(adc / np.abs(adc).std() * 200)
    def word(part):
        return part.astype(np.int16).view(np.uint16).astype(np.float32)
    return decoded.astype(np.complex64), (word(decoded.real) + 1j * word(decoded.imag)).astype(np.complex64)


def test_segment_refuses_raw_words_and_answers_decoded(make_settings, client_for, adc_pair):
    client = client_for(make_settings())
    decoded, raw = adc_pair
    refused = client.post("/v1/segment?input=adc", content=npy_bytes(raw), headers=NPY)
    assert refused.status_code == 422, refused.text
    assert "((x + 32768) % 65536) - 32768" in refused.json()["detail"]
    assert client.post("/v1/segment?input=adc", content=npy_bytes(decoded), headers=NPY).status_code == 200


def test_a_stream_refuses_raw_words(make_settings, client_for, adc_pair):
    client = client_for(make_settings())
    decoded, raw = adc_pair
    stream_id = client.post("/v1/streams").json()["id"]
    refused = client.post(f"/v1/streams/{stream_id}/frames?seq=0&input=adc", content=npy_bytes(raw), headers=NPY)
    assert refused.status_code == 422 and "raw unsigned 16-bit words" in refused.json()["detail"]
    taken = client.post(f"/v1/streams/{stream_id}/frames?seq=0&input=adc", content=npy_bytes(decoded), headers=NPY)
    assert taken.status_code == 200, taken.text
