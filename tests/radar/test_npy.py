"""Safe .npy header parsing: plain headers parse, hostile ones are refused with a DataError before evaluation."""

from __future__ import annotations

import io

import numpy as np
import pytest

from radar.errors import DataError
from radar.io.npy import MAX_HEADER_LEN, decode_npy, parse_npy_header


def _npy(header_text: str, major: int = 1) -> bytes:
    body = header_text.encode("latin1")
    length = len(body).to_bytes(2 if major == 1 else 4, "little")
    return b"\x93NUMPY" + bytes([major, 0]) + length + body


def test_plain_header_parses_and_round_trips():
    array = np.arange(24, dtype=np.complex64).reshape(2, 3, 4)
    buf = io.BytesIO()
    np.save(buf, array)
    header = parse_npy_header(buf.getvalue()[:256])
    assert (header.shape, header.dtype, header.fortran_order) == ((2, 3, 4), np.dtype(np.complex64), False)
    assert np.array_equal(decode_npy(buf.getvalue(), shape=(2, 3, 4)), array)


@pytest.mark.parametrize(("text", "message"), [
    ("-" * 60000 + "1", "oversized .npy header"),  # MemoryError inside ast.literal_eval before the bound
    ("-" * 5000 + "1", "sign characters"),  # RecursionError before the bound
    ("[" * 4000 + "]" * 4000, "nested 4000 deep"),
    ("[" * 300 + "]" * 300, "nested 300 deep"),
    ("{'descr': '<c8', 'fortran_order': False, 'shape': ((((((1,),),),),),)}", "nested 7 deep"),
    ("{'descr': '<c8', 'fortran_order': False, 'shape': (- -  -1,)}", "a run of 3 sign characters"),
    ("{'descr': '<c8', 'fortran_order': False, 'shape': (-1,)}", "malformed .npy shape"),
])
def test_hostile_header_is_refused_before_evaluation(text, message):
    with pytest.raises(DataError, match=message):
        parse_npy_header(_npy(text, major=2 if len(text) > 65535 else 1))


def test_length_bound_is_numpys():
    text = "{'descr': '<f4', 'fortran_order': False, 'shape': (2,)}"
    padded = text + " " * (MAX_HEADER_LEN - len(text))
    assert parse_npy_header(_npy(padded)).shape == (2,)
    with pytest.raises(DataError, match=f"at most {MAX_HEADER_LEN}"):
        parse_npy_header(_npy(padded + " "))
