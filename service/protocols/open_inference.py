"""The Open Inference Protocol's (KServe V2) tensors: a request's JSON header and binary tensor data into numpy
arrays, and numpy outputs into the answer, JSON or binary (the binary tensor data extension).

A request is a JSON object ``{"inputs": [{"name", "shape", "datatype", "data" | "parameters": {"binary_data_size":
N}}], "outputs": [{"name", "parameters": {"binary_data": bool}}], "parameters": {"binary_data_output": bool}}``;
with the binary extension the body is that JSON (``Inference-Header-Content-Length`` bytes) followed by each
binary input's raw little-endian bytes in the inputs' order. Every mistake is a :class:`ProtocolError` naming what
was expected, raised before anything the size of a tensor is allocated.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.protocols.json_tensors import JsonTensorError, NumericList, max_json_body, split_request

HEADER_LENGTH = "Inference-Header-Content-Length"
DATATYPES = {"BOOL": "?", "UINT8": "u1", "UINT16": "<u2", "UINT32": "<u4", "UINT64": "<u8", "INT8": "i1",
             "INT16": "<i2", "INT32": "<i4", "INT64": "<i8", "FP16": "<f2", "FP32": "<f4", "FP64": "<f8"}
DATATYPE_OF = {np.dtype(code).newbyteorder("<").str: name for name, code in DATATYPES.items()}
# input name -> (the shapes it may have, accepted datatypes)
ExpectedInputs = dict[str, tuple[tuple[tuple[int, ...], ...], tuple[str, ...]]]
MAX_HEADER_BYTES = 1 << 16  # a binary request's JSON header: names, shapes and parameters, never the data


class ProtocolError(Exception):
    """A request the protocol cannot read: ``status`` and a message saying what was expected."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class RequestedOutput:
    name: str
    binary: bool


@dataclass(frozen=True)
class InferRequest:
    """A parsed request: its id, its tensors by name (checked shape and datatype) and the outputs it asks for."""

    id: str | None
    inputs: dict[str, np.ndarray]
    outputs: tuple[RequestedOutput, ...] | None  # None: every output
    binary_output: bool


MAX_HEADER_LENGTH_DIGITS = len(str(MAX_HEADER_BYTES))


def _json_header(body: bytes | bytearray | memoryview, header_length: str | None
                 ) -> tuple[dict[str, Any], memoryview, dict[str, NumericList]]:
    """The request's JSON (its numeric ``data`` lists cut out, see service.protocols.json_tensors), the binary
    tensor data after it and the cut lists by marker."""
    view = memoryview(body)
    if header_length is None:
        try:
            parsed, lists = split_request(body)
        except JsonTensorError as exc:
            raise ProtocolError(400, str(exc)) from None
        binary = view[len(body):]
    else:
        digits = header_length.lstrip("0") if header_length.isascii() and header_length.isdigit() else None
        if digits is None or len(digits) > MAX_HEADER_LENGTH_DIGITS or int(digits or "0") > len(body):
            raise ProtocolError(400, f"{HEADER_LENGTH} {header_length[:24]!r}: expected the JSON header's length in "
                                     f"bytes, at most the body's {len(body)} and at most {MAX_HEADER_BYTES}")
        n = int(digits or "0")
        if n > MAX_HEADER_BYTES:
            raise ProtocolError(400, f"{HEADER_LENGTH} {n}: a JSON header of at most {MAX_HEADER_BYTES} bytes is "
                                     "accepted with binary tensor data")
        header, binary, lists = bytes(view[:n]), view[n:], {}
        try:
            parsed = json.loads(header)
        except (ValueError, RecursionError) as exc:
            raise ProtocolError(400, f"the request is not a JSON inference request ({str(exc)[:120]})") from None
    if not isinstance(parsed, dict) or not isinstance(parsed.get("inputs"), list) or not parsed["inputs"]:
        raise ProtocolError(400, "expected a JSON object with a non-empty list 'inputs'")
    return parsed, binary, lists


def _parameters(spec: dict[str, Any], where: str) -> dict[str, Any]:
    """``spec``'s "parameters": an object (absent or null: none); 400 for any other type."""
    parameters = spec.get("parameters")
    if parameters is None:
        return {}
    if not isinstance(parameters, dict):
        raise ProtocolError(400, f"{where}'parameters' must be a JSON object, got {type(parameters).__name__} "
                                 f"{str(parameters)[:40]!r}")
    return parameters


def _tensor(spec: Any, binary: memoryview, offset: int, expected: ExpectedInputs,
            lists: dict[str, NumericList]) -> tuple[str, np.ndarray, int]:
    """One input as an array (its shape and datatype checked against ``expected`` before any data is read) and the
    binary bytes it took."""
    if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
        raise ProtocolError(400, "each input must be an object with a 'name'")
    name = spec["name"]
    if name not in expected:
        raise ProtocolError(400, f"unknown input {name[:64]!r}: the model takes one of {sorted(expected)}")
    shapes, datatypes = expected[name]
    given = spec.get("shape")
    shape = next((s for s in shapes if given == list(s)), None)
    if shape is None:
        missing = (" (its trailing axis of 2 is missing: I and Q, or real and imaginary parts)"
                   if isinstance(given, list) and given + [2] in [list(s) for s in shapes] else "")
        raise ProtocolError(400, f"input {name!r} has shape {str(given)[:80]}, expected "
                                 f"{' or '.join(str(list(s)) for s in shapes)}{missing}")
    if spec.get("datatype") not in datatypes:
        raise ProtocolError(400, f"input {name!r} has datatype {str(spec.get('datatype'))[:24]!r}, expected one of "
                                 f"{list(datatypes)}")
    dtype = np.dtype(DATATYPES[spec["datatype"]])
    count = int(np.prod(shape))
    size = count * dtype.itemsize
    parameters = _parameters(spec, f"input {name!r}: ")
    if "binary_data_size" in parameters:
        declared = parameters["binary_data_size"]
        if type(declared) is not int or declared != size or offset + size > len(binary):
            raise ProtocolError(400, f"input {name!r}: binary_data_size {str(declared)[:24]} with "
                                     f"{len(binary) - offset} bytes left, expected {size} ({list(shape)} "
                                     f"{spec['datatype']})")
        return name, np.frombuffer(binary[offset:offset + size], dtype).reshape(shape), size
    data = spec.get("data")
    if not (isinstance(data, str) and data in lists):
        what = ("'data' must be a list of JSON numbers (no strings, booleans or NaN)" if "data" in spec
                else "expected 'data' (a list of numbers) or parameters.binary_data_size")
        raise ProtocolError(400, f"input {name!r}: {what}")
    try:
        values = lists[data].values(name, dtype, count)
    except JsonTensorError as exc:
        raise ProtocolError(400, str(exc)) from None
    return name, values.reshape(shape), 0


def _outputs(parsed: dict[str, Any], known: tuple[str, ...]) -> tuple[tuple[RequestedOutput, ...] | None, bool]:
    binary_default = _parameters(parsed, "").get("binary_data_output", False)
    if not isinstance(binary_default, bool):
        raise ProtocolError(400, f"parameters.binary_data_output must be true or false, got {str(binary_default)[:24]}")
    if parsed.get("outputs") is None:
        return None, binary_default
    chosen = []
    for spec in parsed["outputs"] if isinstance(parsed["outputs"], list) else [None]:
        if not isinstance(spec, dict) or spec.get("name") not in known:
            raise ProtocolError(400, f"unknown output {str(spec)[:80]}: the model answers {list(known)}")
        binary = _parameters(spec, f"output {spec['name']!r}: ").get("binary_data", binary_default)
        if not isinstance(binary, bool):
            raise ProtocolError(400, f"output {spec['name']!r}: parameters.binary_data must be true or false, got "
                                     f"{str(binary)[:24]}")
        chosen.append(RequestedOutput(spec["name"], binary))
    return tuple(chosen), binary_default


def parse_request(body: bytes | bytearray | memoryview, header_length: str | None, expected: ExpectedInputs,
                  outputs: tuple[str, ...]) -> InferRequest:
    """The request in ``body``; ``expected``: input name -> (the shapes it may have, accepted datatypes);
    ``outputs``: the names the model answers. CPU work of the size of the body: call it off the event loop."""
    parsed, view, lists = _json_header(body, header_length)
    chosen, binary_output = _outputs(parsed, outputs)  # the small fields first, before any tensor is read
    offset, inputs = 0, {}
    for spec in parsed["inputs"]:
        name, array, used = _tensor(spec, view, offset, expected, lists)
        if name in inputs:
            raise ProtocolError(400, f"input {name!r} given twice")
        inputs[name], offset = array, offset + used
    if offset != len(view):
        raise ProtocolError(400, f"the body holds {len(view) - offset} binary bytes no input's binary_data_size "
                                 "accounts for")
    request_id = parsed.get("id")
    return InferRequest(request_id if isinstance(request_id, str) else None, inputs, chosen, binary_output)


def max_input_values(expected: ExpectedInputs) -> int:
    """The numbers of the model's largest input (one request sends one input)."""
    return max(int(np.prod(shape)) for shapes, _ in expected.values() for shape in shapes)


def max_request_bytes(expected: ExpectedInputs, *, binary: bool) -> int:
    """The longest body a request for ``expected`` could need: with binary tensor data, the JSON header and the
    largest input in its widest datatype; as JSON, the largest input's numbers (service.protocols.json_tensors)."""
    if not binary:
        return max_json_body(max_input_values(expected))
    return MAX_HEADER_BYTES + max(int(np.prod(shape)) * max(np.dtype(DATATYPES[d]).itemsize for d in datatypes)
                                  for shapes, datatypes in expected.values() for shape in shapes)


def encode_response(model: str, request_id: str | None, tensors: dict[str, np.ndarray],
                    parameters: dict[str, dict[str, Any]], chosen: tuple[RequestedOutput, ...]
                    ) -> tuple[bytes, int | None]:
    """The answer's body and, when any output is binary, the length of its JSON header."""
    outputs, blobs = [], []
    for output in chosen:
        array = tensors[output.name]
        entry: dict[str, Any] = {"name": output.name, "shape": list(array.shape)}
        if array.dtype.kind in "SO":  # BYTES: each element a length-prefixed string in binary
            entry["datatype"] = "BYTES"
            values = [bytes(v) for v in array.ravel()]
            binary = b"".join(len(v).to_bytes(4, "little") + v for v in values)
            data: Any = [v.decode() for v in values]
        else:
            array = array.astype(array.dtype.newbyteorder("<"), copy=False)
            entry["datatype"] = DATATYPE_OF[array.dtype.str]
            binary, data = None, None
        entry["parameters"] = dict(parameters.get(output.name, {}))
        if output.binary:
            blob = binary if binary is not None else np.ascontiguousarray(array).tobytes()
            entry["parameters"]["binary_data_size"] = len(blob)
            blobs.append(blob)
        else:
            entry["data"] = data if data is not None else array.ravel().tolist()
        outputs.append(entry)
    header = json.dumps({"model_name": model, "id": request_id or "", "outputs": outputs}).encode()
    if not blobs:
        return header, None
    return header + b"".join(blobs), len(header)
