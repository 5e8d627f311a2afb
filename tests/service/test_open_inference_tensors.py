"""The Open Inference Protocol's tensor codec (service/protocols/open_inference.py) on its own: JSON and binary
inputs read as arrays, every mistake refused with a message naming what was expected, outputs encoded as
tritonclient decodes them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tritonclient.http import InferResult

from service.protocols.open_inference import ProtocolError, RequestedOutput, encode_response, parse_request

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
    (_json(data=["x"] * 6), None, "must be a list of JSON numbers"),
    (_json(data=(1.0,)), None, "holds 1 values"),
    (_json(data=None), None, "expected 'data'"),
    (_json(outputs=[{"name": "x"}]), None, "unknown output"),
    (b'{"inputs": []}', "999", "at most the body's"),
    (b"[" * 60_000, None, "not a JSON inference request"),
    (b"[" * 100_000, None, "100000 bytes or more besides its lists of numbers"),
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


@pytest.mark.parametrize("body, length, words", [
    (_json(parameters=[1]), None, "'parameters' must be a JSON object, got list"),
    (_json(parameters="x"), None, "'parameters' must be a JSON object, got str"),
    (_json(parameters={"binary_data_output": "yes"}), None, "binary_data_output must be true or false"),
    (_json(outputs=[{"name": "labels", "parameters": [1]}]), None, "output 'labels': 'parameters' must be"),
    (_json(outputs=[{"name": "labels", "parameters": "binary"}]), None, "output 'labels': 'parameters' must be"),
    (_json(outputs=[{"name": "labels", "parameters": {"binary_data": 1}}]), None, "binary_data must be true or"),
    (json.dumps({"inputs": [{"name": "log_power", "shape": [2, 3], "datatype": "FP32",
                             "parameters": "binary_data_size"}]}).encode(), None, "input 'log_power': 'parameters'"),
    (b'{"inputs": [{}]}', "9" * 4301, "Inference-Header-Content-Length '9999"),
    (b'{"inputs": [{}]}', "0" * 5000 + "1", "not a JSON inference request"),
])
def test_fields_of_the_wrong_type_are_refused_not_a_server_error(body, length, words):
    with pytest.raises(ProtocolError, match=words) as refused:
        parse_request(body, length, EXPECTED, OUTPUTS)
    assert refused.value.status == 400


def _iq(data) -> bytes:
    return json.dumps({"inputs": [{"name": "adc_iq", "shape": [4, 5, 2], "datatype": "INT16", "data": data}]}).encode()


@pytest.mark.parametrize("data, words", [
    (["1"] * 40, "must be a list of JSON numbers"),
    ([True] * 40, "must be a list of JSON numbers"),
    ([1.5] + [0] * 39, "value 1.5 at 0 is not int16"),
    ([0] * 39 + [40000], r"value 40000.0 at 39 is not int16: integers in \[-32768, 32767\]"),
])
def test_json_numbers_must_be_numbers_of_the_datatype(data, words):
    with pytest.raises(ProtocolError, match=words):
        parse_request(_iq(data), None, EXPECTED, OUTPUTS)


def test_json_numbers_nested_or_flat_read_as_sent_and_malformed_lists_are_refused():
    iq = np.arange(-20, 20, dtype=np.int16).reshape(4, 5, 2)
    for data in (iq.tolist(), iq.ravel().tolist()):
        np.testing.assert_array_equal(parse_request(_iq(data), None, EXPECTED, OUTPUTS).inputs["adc_iq"], iq)
    cube = np.array([[1e-30, -2.5, 3], [4e5, 5, 6]], np.float32)
    body = json.dumps({"inputs": [{"name": "log_power", "shape": [2, 3], "datatype": "FP32", "data": cube.tolist()}],
                       "id": '"data": [1]'}).encode()
    parsed = parse_request(body, None, EXPECTED, OUTPUTS)
    np.testing.assert_array_equal(parsed.inputs["log_power"], cube)
    assert parsed.id == '"data": [1]'
    malformed = {b"[1, 2, 3, 4, 5, 6,]": "holds 7 values", b"[1 2, 3, 4, 5, 6]": "holds 5 values",
                 b"[[1, 2, 3], [4, 5, 6]]]": "brackets do not nest", b"[1, 2], [3, 4, 5, 6]": "brackets do not nest",
                 b"[1, 2, 3, -, 5, 6]": "not a JSON number", b"[1, 2][, 3, 4, 5, 6]": "not a JSON list of numbers",
                 b"[1 2, 3, 4, 5, 6, 7]": "misplaced comma, bracket or space"}
    for text, words in malformed.items():
        body = b'{"inputs": [{"name": "log_power", "shape": [2, 3], "datatype": "FP32", "data": ' + text + b"}]}"
        with pytest.raises(ProtocolError, match=words):
            parse_request(body, None, EXPECTED, OUTPUTS)


def test_a_json_request_is_read_without_a_python_object_per_number():
    """2 M numbers: json.loads took about 32 bytes of Python objects each; read by numpy, the peak is the text and
    the array (tracemalloc counts numpy's buffers)."""
    import tracemalloc

    n = 2_000_000
    expected = {"log_power": (((n,),), ("FP32",))}
    body = b'{"inputs": [{"name": "log_power", "shape": [%d], "datatype": "FP32", "data": [' % n + \
        b", ".join([b"1.5"] * n) + b"]}]}"
    tracemalloc.start()
    try:
        parsed = parse_request(body, None, expected, OUTPUTS)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert parsed.inputs["log_power"].shape == (n,) and float(parsed.inputs["log_power"][-1]) == 1.5
    assert peak < 3 * len(body) + 8 * n, (peak, len(body))
