"""The upload gate's bookkeeping: bounds in total and per tenant, chunked bodies charged when their size
is known, and every place given back whatever happened to the upload."""

from __future__ import annotations

import re

import numpy as np
import pytest

from service.http.errors import ApiError
from service.inputs.upload import ExpectedCube, UploadGate, check_declared_length, check_values
from service.schemas import InputKind
from service.settings import Settings

MB = 10**6


def test_one_tenant_cannot_take_every_place_and_places_are_given_back(tmp_path):
    gate = UploadGate(Settings(data_dir=tmp_path, max_body_bytes=2 * MB, max_upload_bytes=10 * MB,
                               max_tenant_upload_bytes=4 * MB, max_uploads=6, max_tenant_uploads=3))
    with gate.admit("acme", 2 * MB), gate.admit("acme", 2 * MB):
        with pytest.raises(ApiError, match="tenant 'acme' has uploads of 4000000 bytes"):
            with gate.admit("acme", 1):
                pass
        with gate.admit("acme", None) as chunked:  # a chunked body: charged once its header says how big
            with pytest.raises(ApiError, match="per tenant"):
                chunked.charge(MB)
        with gate.admit("globex", 2 * MB), gate.admit("globex", 2 * MB):  # another tenant is not blocked
            with pytest.raises(ApiError, match="limit: 10000000 bytes"):
                with gate.admit("initech", 3 * MB):
                    pass
    with pytest.raises(ApiError, match="limit: 3 per tenant"):
        with gate.admit("acme", None), gate.admit("acme", None), gate.admit("acme", None), gate.admit("acme", None):
            pass
    assert (gate.uploads, gate.bytes, gate.tenant_uploads, gate.tenant_bytes) == (0, 0, {}, {})


def test_declared_lengths_and_values_beyond_the_model_are_refused():
    expected = ExpectedCube("tiny", (4, 4, 2), InputKind.complex)
    adc = ExpectedCube("tiny", (4, 2, 2), InputKind.adc)
    check_declared_length(expected.max_body_bytes(), [adc, expected])
    with pytest.raises(ApiError, match=f"at most {expected.max_body_bytes()} bytes") as refused:
        check_declared_length(expected.max_body_bytes() + 1, [adc, expected])
    assert refused.value.status == 413 and "with ?input=complex" in refused.value.message
    cube = np.ones((4, 4, 2), np.complex64)
    check_values(cube, expected)
    for value, message in ((3e38, "magnitude 3e+38"), (-2e15j, "magnitude 2e+15"), (np.nan, "NaN")):
        bad = cube.copy()
        bad[1, 2, 1] = value
        with pytest.raises(ApiError, match=re.escape(message)) as refused:
            check_values(np.asfortranarray(bad) if np.isnan(value) else bad, expected)
        assert refused.value.status == 422
    log_power = ExpectedCube("tiny", (4, 4, 2), InputKind.log_power)
    # log power beyond the transform's range is refused by the input-kind rule first, naming the likely mistake
    with pytest.raises(ApiError, match=r"log power down to -1e\+300 dB"):
        check_values(np.full((4, 4, 2), -1e300), log_power)
    with pytest.raises(ApiError, match=r"linear magnitude or power\?"):
        check_values(np.full((4, 4, 2), 1e300), log_power)
    magnitude = ExpectedCube("tiny", (4, 4, 2), InputKind.magnitude)
    peaks = np.full((4, 4, 2), 1.0)
    peaks[0, 0, 0] = 1e300  # a plausible magnitude cube's shape, a value the float32 transform cannot square
    with pytest.raises(ApiError, match=r"real and imaginary parts within \[-1e\+15, 1e\+15\]"):
        check_values(peaks, magnitude)
