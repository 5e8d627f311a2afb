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


def _json_header(body: bytes | bytearray, header_length: str | None) -> tuple[dict[str, Any], memoryview]:
    view = memoryview(body)
    if header_length is None:
        header, binary = body, view[len(body):]
    else:
        if not (header_length.isascii() and header_length.isdigit()) or int(header_length) > len(body):
            raise ProtocolError(400, f"{HEADER_LENGTH} {header_length[:24]!r}: expected the JSON header's length in "
                                     f"bytes, at most the body's {len(body)}")
        n = int(header_length)
        if n > MAX_HEADER_BYTES:
            raise ProtocolError(400, f"{HEADER_LENGTH} {n}: a JSON header of at most {MAX_HEADER_BYTES} bytes is "
                                     "accepted with binary tensor data")
        header, binary = bytes(view[:n]), view[n:]
    try:
        parsed = json.loads(header)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(400, f"the request is not a JSON inference request ({str(exc)[:120]})") from None
    if not isinstance(parsed, dict) or not isinstance(parsed.get("inputs"), list) or not parsed["inputs"]:
        raise ProtocolError(400, "expected a JSON object with a non-empty list 'inputs'")
    return parsed, binary


def _tensor(spec: Any, binary: memoryview, offset: int, expected: ExpectedInputs) -> tuple[str, np.ndarray, int]:
    """One input as an array (its shape and datatype checked against ``expected`` before any data is read) and the
    binary bytes it took."""
    if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
        raise ProtocolError(400, "each input must be an object with a 'name'")
    name = spec["name"]
    if name not in expected:
        raise ProtocolError(400, f"unknown input {name!r}: the model takes one of {sorted(expected)}")
    shapes, datatypes = expected[name]
    given = spec.get("shape")
    shape = next((s for s in shapes if given == list(s)), None)
    if shape is None:
        missing = (" (its trailing axis of 2 is missing: I and Q, or real and imaginary parts)"
                   if isinstance(given, list) and given + [2] in [list(s) for s in shapes] else "")
        raise ProtocolError(400, f"input {name!r} has shape {given!r}, expected "
                                 f"{' or '.join(str(list(s)) for s in shapes)}{missing}")
    if spec.get("datatype") not in datatypes:
        raise ProtocolError(400, f"input {name!r} has datatype {spec.get('datatype')!r}, expected one of "
                                 f"{list(datatypes)}")
    dtype = np.dtype(DATATYPES[spec["datatype"]])
    size = int(np.prod(shape)) * dtype.itemsize
    parameters = spec.get("parameters") or {}
    if "binary_data_size" in parameters:
        if parameters["binary_data_size"] != size or offset + size > len(binary):
            raise ProtocolError(400, f"input {name!r}: binary_data_size {parameters['binary_data_size']!r} with "
                                     f"{len(binary) - offset} bytes left, expected {size} ({list(shape)} "
                                     f"{spec['datatype']})")
        return name, np.frombuffer(binary[offset:offset + size], dtype).reshape(shape), size
    data = spec.get("data")
    if not isinstance(data, list):
        raise ProtocolError(400, f"input {name!r}: expected 'data' (a list) or parameters.binary_data_size")
    try:
        array = np.asarray(data, dtype=dtype)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ProtocolError(400, f"input {name!r}: 'data' is not {spec['datatype']} numbers ({exc})") from None
    if array.size != int(np.prod(shape)):
        raise ProtocolError(400, f"input {name!r}: 'data' holds {array.size} values, expected {int(np.prod(shape))}")
    return name, array.reshape(shape), 0


def _outputs(parsed: dict[str, Any], known: tuple[str, ...]) -> tuple[tuple[RequestedOutput, ...] | None, bool]:
    binary_default = bool((parsed.get("parameters") or {}).get("binary_data_output", False))
    if parsed.get("outputs") is None:
        return None, binary_default
    chosen = []
    for spec in parsed["outputs"] if isinstance(parsed["outputs"], list) else [None]:
        if not isinstance(spec, dict) or spec.get("name") not in known:
            raise ProtocolError(400, f"unknown output {spec!r}: the model answers {list(known)}")
        binary = (spec.get("parameters") or {}).get("binary_data", binary_default)
        chosen.append(RequestedOutput(spec["name"], bool(binary)))
    return tuple(chosen), binary_default


def parse_request(body: bytes | bytearray, header_length: str | None, expected: ExpectedInputs,
                  outputs: tuple[str, ...]) -> InferRequest:
    """The request in ``body``; ``expected``: input name -> (the shapes it may have, accepted datatypes);
    ``outputs``: the names the model answers."""
    parsed, view = _json_header(body, header_length)
    offset, inputs = 0, {}
    for spec in parsed["inputs"]:
        name, array, used = _tensor(spec, view, offset, expected)
        if name in inputs:
            raise ProtocolError(400, f"input {name!r} given twice")
        inputs[name], offset = array, offset + used
    if offset != len(view):
        raise ProtocolError(400, f"the body holds {len(view) - offset} binary bytes no input's binary_data_size "
                                 "accounts for")
    chosen, binary_output = _outputs(parsed, outputs)
    request_id = parsed.get("id")
    return InferRequest(request_id if isinstance(request_id, str) else None, inputs, chosen, binary_output)


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
