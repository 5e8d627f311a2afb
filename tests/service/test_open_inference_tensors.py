"""The Open Inference Protocol's tensor codec (service/open_inference.py) on its own: JSON and binary inputs read as
arrays, every mistake refused with a message naming what was expected, outputs encoded as tritonclient decodes them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tritonclient.http import InferResult

from service.open_inference import ProtocolError, RequestedOutput, encode_response, parse_request

EXPECTED = {"log_power": (((2, 3),), ("FP16", "FP32")), "complex": (((2, 3, 2),), ("FP32",)),
            "adc_iq": (((4, 5, 2), (5, 4, 2)), ("INT16",))}
OUTPUTS = ("labels", "objects", "compute")


def _binary(name: str, array: np.ndarray, datatype: str, *, size: int | None = None, **extra) -> tuple[bytes, str]:
    header = json.dumps({"inputs": [{"name": name, "shape": list(array.shape), "datatype": datatype,
                                     "parameters": {"binary_data_size": array.nbytes if size is None else size}}],
                         **extra}).encode()
    return header + array.tobytes(), str(len(header))


def test_json_and_binary_inputs_read_as_the_arrays_sent():
    cube = np.arange(6, dtype=np.float32).reshape(2, 3)
    body = json.dumps({"id": "a", "inputs": [{"name": "log_power", "shape": [2, 3], "datatype": "FP32",
                                              "data": cube.tolist()}]}).encode()
    parsed = parse_request(body, None, EXPECTED, OUTPUTS)
    np.testing.assert_array_equal(parsed.inputs["log_power"], cube)
    assert parsed.id == "a" and parsed.outputs is None
    body, length = _binary("log_power", cube.astype(np.float16), "FP16",
                           outputs=[{"name": "labels", "parameters": {"binary_data": True}}, {"name": "objects"}])
    parsed = parse_request(bytearray(body), length, EXPECTED, OUTPUTS)
    np.testing.assert_array_equal(parsed.inputs["log_power"], cube)
    assert parsed.outputs == (RequestedOutput("labels", True), RequestedOutput("objects", False))


def _json(shape=(2, 3), datatype="FP32", data=(0.0,) * 6, **extra) -> bytes:
    spec = {"name": "log_power", "shape": list(shape), "datatype": datatype}
    return json.dumps({"inputs": [spec if data is None else {**spec, "data": list(data)}], **extra}).encode()


@pytest.mark.parametrize("body, length, words", [
    (b"\x00\xff", None, "not a JSON inference request"),
    (b"[1]", None, "non-empty list 'inputs'"),
    (_json(datatype="FP64"), None, "datatype 'FP64'"),
    (_json(shape=(3, 2)), None, r"expected \[2, 3\]"),
    (_json(data=["x"] * 6), None, "not FP32"),
    (_json(data=(1.0,)), None, "holds 1 values"),
    (_json(data=None), None, "expected 'data'"),
    (_json(outputs=[{"name": "x"}]), None, "unknown output"),
    (b'{"inputs": []}', "999", "at most the body's"),
    (b"[" * 100_000, None, "not a JSON inference request"),
])
def test_malformed_requests_are_refused_with_what_was_expected(body, length, words):
    with pytest.raises(ProtocolError, match=words) as refused:
        parse_request(body, length, EXPECTED, OUTPUTS)
    assert refused.value.status == 400


def test_an_input_of_several_shapes_takes_each_and_names_them_all():
    for shape in ((4, 5, 2), (5, 4, 2)):
        iq = np.arange(40, dtype=np.int16).reshape(shape)
        body, length = _binary("adc_iq", iq, "INT16")
        np.testing.assert_array_equal(parse_request(body, length, EXPECTED, OUTPUTS).inputs["adc_iq"], iq)
    body, length = _binary("adc_iq", np.zeros((4, 5), np.int16), "INT16")
    with pytest.raises(ProtocolError, match=r"expected \[4, 5, 2\] or \[5, 4, 2\] \(its trailing axis of 2 is "
                                            "missing"):
        parse_request(body, length, EXPECTED, OUTPUTS)
    body, length = _binary("adc_iq", np.zeros((4, 5, 2), np.float32), "FP32")
    with pytest.raises(ProtocolError, match=r"datatype 'FP32', expected one of \['INT16'\]"):
        parse_request(body, length, EXPECTED, OUTPUTS)


def test_binary_sizes_must_add_up():
    cube = np.zeros((2, 3), np.float32)
    body, length = _binary("log_power", cube, "FP32", size=12)
    with pytest.raises(ProtocolError, match="binary_data_size 12"):
        parse_request(body, length, EXPECTED, OUTPUTS)
    body, length = _binary("log_power", cube, "FP32")
    with pytest.raises(ProtocolError, match="4 binary bytes"):
        parse_request(body + b"\0" * 4, length, EXPECTED, OUTPUTS)


def test_outputs_decode_with_tritonclient():
    tensors = {"labels": np.arange(6, dtype=np.uint8).reshape(2, 3), "objects": np.ones((1, 8), np.float32),
               "compute": np.array([b'{"macs": 1}'], object)}
    chosen = (RequestedOutput("labels", True), RequestedOutput("objects", False), RequestedOutput("compute", True))
    body, length = encode_response("m", "r", tensors, {"objects": {"columns": "a"}}, chosen)
    result = InferResult.from_response_body(body, header_length=length)
    np.testing.assert_array_equal(result.as_numpy("labels"), tensors["labels"])
    np.testing.assert_array_equal(result.as_numpy("objects"), tensors["objects"])
    assert result.as_numpy("compute")[0] == b'{"macs": 1}'
    assert result.get_output("objects")["parameters"] == {"columns": "a"}
