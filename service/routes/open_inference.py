"""The Open Inference Protocol (KServe V2, as Triton, KServe and MLServer speak it) beside the service's own API.

``GET /v2`` (server metadata), ``GET /v2/health/live``, ``GET /v2/health/ready``, ``GET /v2/models/{name}``
(metadata: one input per input kind, with its shape and datatypes), ``GET /v2/models/{name}/ready`` and
``POST /v2/models/{name}/infer``. A request sends exactly one input, named after its input kind:

    complex    FP32/FP64 [R, A, D, 2]   the complex RAD cube, real and imaginary parts on a trailing axis of 2
    magnitude  FP16/FP32/FP64 [R, A, D] its linear magnitude
    log_power  FP16/FP32/FP64 [R, A, D] its log power in dB
    adc        FP32/FP64 [S, C, V, 2]   raw ADC samples (samples, chirps, virtual elements), real and imaginary
    adc_iq     INT16 [S, C, V, 2] or [C, RX, S, 2]  the same samples as a TI radar gives them, int16 with I and Q on a
               trailing axis of 2, in either layout /v1/segment?input=adc takes (service.inputs.adc_upload: "sck",
               or "ti" (chirps, rx, samples), told apart by shape); UINT16 is read too, only to be refused as /v1
               refuses undecoded words

and gets the outputs ``labels`` (UINT8 [R, A, D]), ``ra_mask`` (UINT8 [R, A]), ``rd_mask`` (UINT8 [R, D]),
``objects`` (FP32 [K, 8], columns in its parameters) and ``compute`` (BYTES [1]: the request's compute block, id and
the tenant's usage as JSON), all of them unless ``outputs`` names some. Tensors travel as JSON or with the binary
tensor data extension. An inference goes the way of ``POST /v1/segment`` (the same checks of the cube, model slot,
quota lease and billing: :func:`service.routes.segment.run_billed`). Errors raised here answer the protocol's
``{"error": "message"}`` with their 4xx/503 status.
"""

from __future__ import annotations

import json
import time
from dataclasses import fields
from typing import Any

import numpy as np
from fastapi import APIRouter, Path, Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from models.erasenet.model import SegmentedObject
from radar.adc import LAYOUTS, adc_shape
from service.accounting.tenants import Principal
from service.deps import Caller, ServiceState, State
from service.http.errors import ApiError
from service.inference import ServedModel
from service.inputs.adc_upload import AXES, AdcFrameInput
from service.inputs.json_body import declared_length
from service.inputs.upload import ExpectedCube, check_values, paced
from service.protocols.json_tensors import MAX_VALUE_CHARS, max_json_values
from service.protocols.open_inference import (
    HEADER_LENGTH,
    ExpectedInputs,
    InferRequest,
    ProtocolError,
    RequestedOutput,
    encode_response,
    max_input_values,
    max_request_bytes,
    parse_request,
)
from service.routes.errors_doc import error_responses
from service.routes.segment import Admitted, run_billed
from service.schemas import InputKind, MaskEncoding

router = APIRouter(tags=["open inference protocol"])

OUTPUTS = ("labels", "ra_mask", "rd_mask", "objects", "compute")
OBJECT_COLUMNS = tuple(f.name for f in fields(SegmentedObject) if f.name != "class_name")
INPUTS = {"complex": InputKind.complex, "magnitude": InputKind.magnitude, "log_power": InputKind.log_power,
          "adc": InputKind.adc, "adc_iq": InputKind.adc}  # input name -> the input kind it holds
_DATATYPES = {"complex": ("FP32", "FP64"), "adc": ("FP32", "FP64"), "adc_iq": ("INT16", "UINT16"),
              "magnitude": ("FP16", "FP32", "FP64"), "log_power": ("FP16", "FP32", "FP64")}
UNDECLARED = ("UINT16",)  # read only to be refused (undecoded words, as on /v1): not in the model's metadata
_COMPLEX = {np.dtype("<f4"): np.complex64, np.dtype("<f8"): np.complex128}
ModelName = Path(max_length=64, description="a served model's name (GET /v1/models)")
ModelVersion = Path(max_length=64, description="the model's version: each served model has one, '1'")
VERSIONS = ("1",)


class ProtocolErrorBody(BaseModel):
    """The Open Inference Protocol's error answer."""

    error: str


_WHY = {400: "not an inference request the model takes: JSON, inputs, shapes, datatypes, binary sizes",
        404: "no served model of that name", 408: "the body fell behind the upload pace",
        413: "a body (or a JSON body's count of numbers) larger than the model's largest input could need",
        415: "a Content-Type other than application/json or application/octet-stream",
        422: "NaN/Inf or values impossible for the input kind", 429: "the tenant's daily MAC quota",
        503: "not ready, every slot taken, uploads saturated or the ledger down (Retry-After)"}


def protocol_errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI descriptions of the errors a route answers in the protocol's shape (the service's own for failures
    before the route runs: 401 keys, 413 body limit, 422 unknown query parameters)."""
    return {**error_responses(401, 413, 422),
            **{code: {"model": ProtocolErrorBody, "description": _WHY[code]} for code in codes}}


def protocol_error(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    """The protocol's error body."""
    return JSONResponse({"error": message}, status_code=status, headers=headers)


def _input_shapes(served: ServedModel) -> ExpectedInputs:
    """Input name -> (the shapes it may have, accepted datatypes); ``adc_iq``: a frame in each layout of
    service.inputs.adc_upload, with I and Q on a trailing axis of 2."""
    profile = served.net.profile
    shapes = {"complex": [(*profile.shape, 2)], "magnitude": [profile.shape], "log_power": [profile.shape],
              "adc": [(*adc_shape(profile), 2)],
              "adc_iq": [(*shape, 2) for shape in AdcFrameInput(profile).shapes().values()]}
    return {name: (tuple(tuple(shape) for shape in shapes[name]), _DATATYPES[name]) for name in INPUTS}


def _declared(name: str, shapes: tuple[tuple[int, ...], ...], datatypes: tuple[str, ...]) -> dict[str, Any]:
    """An input as the model's metadata declares it: its first shape and datatype, every datatype it takes and, for
    one of several shapes, each with its layout."""
    declared = [datatype for datatype in datatypes if datatype not in UNDECLARED]
    parameters = {"datatypes": ",".join(declared)}
    if len(shapes) > 1:
        parameters["shapes"] = " or ".join(f"{list(shape)} {layout} {AXES[layout]}"
                                           for shape, layout in zip(shapes, LAYOUTS, strict=True))
    return {"name": name, "datatype": declared[0], "shape": list(shapes[0]), "parameters": parameters}


def _served(state: ServiceState, name: str, *, ready: bool = True) -> ServedModel:
    try:
        served = state.pool.get(name)
    except KeyError as exc:
        raise ApiError(404, exc.args[0]) from None
    if ready and not served.ready:
        raise ApiError(503, f"model {name!r} is not ready ({served.stage}): {served.error}",
                       headers={"Retry-After": str(state.settings.retry_after_s)})
    return served


@router.get("/v2", summary="Server metadata (Open Inference Protocol)")
def server_metadata(state: State) -> dict[str, Any]:
    return {"name": "radarseg", "version": "0.1.0", "extensions": ["binary_tensor_data"]}


@router.get("/v2/health/live", summary="Liveness (Open Inference Protocol)")
def live() -> dict[str, bool]:
    return {"live": True}


@router.get("/v2/health/ready", summary="Readiness (Open Inference Protocol)",
            responses={503: {"description": "not ready"}})
def ready(state: State) -> JSONResponse:
    """200 when every model is loaded and the usage ledger is reachable, else 503."""
    is_ready = state.pool.ready and state.ledger_error is None
    return JSONResponse({"ready": is_ready}, status_code=200 if is_ready else 503)


@router.get("/v2/models/{name}/ready", summary="A model's readiness (Open Inference Protocol)",
            responses=protocol_errors(404, 503))
def model_ready(state: State, caller: Caller, name: str = ModelName) -> JSONResponse:
    try:
        served = _served(state, name, ready=False)
    except ApiError as exc:
        return protocol_error(exc.status, exc.message)
    return JSONResponse({"name": name, "ready": served.ready}, status_code=200 if served.ready else 503)


@router.get("/v2/models/{name}", summary="A model's metadata (Open Inference Protocol)",
            responses=protocol_errors(404, 503))
def model_metadata(state: State, caller: Caller, name: str = ModelName) -> JSONResponse:
    """Its inputs (one per input kind; send one) and outputs, with shapes and datatypes."""
    try:
        served = _served(state, name)
    except ApiError as exc:
        return protocol_error(exc.status, exc.message, exc.headers)
    profile = served.net.profile
    R, A, D = profile.shape
    inputs = [_declared(name, shapes, datatypes) for name, (shapes, datatypes) in _input_shapes(served).items()]
    outputs = [{"name": "labels", "datatype": "UINT8", "shape": [R, A, D]},
               {"name": "ra_mask", "datatype": "UINT8", "shape": [R, A]},
               {"name": "rd_mask", "datatype": "UINT8", "shape": [R, D]},
               {"name": "objects", "datatype": "FP32", "shape": [-1, len(OBJECT_COLUMNS)],
                "parameters": {"columns": ",".join(OBJECT_COLUMNS)}},
               {"name": "compute", "datatype": "BYTES", "shape": [1]}]
    return JSONResponse({"name": name, "versions": list(VERSIONS),
                         "platform": f"radarseg-erasenet-{served.spec.runtime}",
                         "inputs": inputs, "outputs": outputs,
                         "parameters": {"preset": profile.name, "class_names": ",".join(served.net.class_names)}})


MEDIA_TYPES = ("application/json", "application/octet-stream")  # or none: tritonclient sends no Content-Type


def _check_media_type(request: Request) -> None:
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type and media_type not in MEDIA_TYPES:
        raise ApiError(415, f"content type {media_type[:64]!r} is not accepted: send a JSON inference request as "
                            f"{' or '.join(MEDIA_TYPES)} (or with no Content-Type)")


def _too_large(what: str, limit: int, name: str, binary: bool) -> ApiError:
    how = ("its JSON header and the binary tensor data of its largest input" if binary else
           f"its largest input's numbers as JSON of at most {MAX_VALUE_CHARS} characters each, and the rest")
    return ApiError(413, f"request body {what} is larger than any request model {name!r} takes: at most {limit} "
                         f"bytes ({how})", headers={"Connection": "close"})


async def _read_body(request: Request, state: ServiceState, tenant: str, served: ServedModel) -> memoryview:
    """The whole body, within what the model's largest input could need (413 at once for a larger declared length,
    as soon as the bytes or a JSON body's commas pass it), the upload gate's bounds and the body pace (408 for a
    stalled upload)."""
    expected = _input_shapes(served)
    binary = request.headers.get(HEADER_LENGTH) is not None
    limit = max_request_bytes(expected, binary=binary)
    max_commas = None if binary else max_json_values(max_input_values(expected))
    length = declared_length(request)
    if length is not None and length > limit:
        raise _too_large(f"of {length} bytes", limit, served.spec.name, binary)
    # a declared length (bounded above) is filled in place, no copy as it grows; np.empty maps its pages as the
    # bytes arrive (bytearray(n) wrote n zeros at once: four slow 64 MiB uploads held 164 MB before sending a byte)
    body: np.ndarray | bytearray = np.empty(length, np.uint8) if length else bytearray()
    received = commas = 0
    with state.uploads.admit(tenant, length) as ticket:
        try:
            async for chunk in paced(request.stream(), state.settings):
                end = received + len(chunk)
                if end > limit:
                    raise _too_large(f"of more than {limit} bytes", limit, served.spec.name, binary)
                if max_commas is not None:
                    commas += chunk.count(b",")
                    if commas > max_commas:
                        raise ApiError(413, f"the JSON request holds more than {max_commas} values: model "
                                            f"{served.spec.name!r}'s largest input has {max_input_values(expected)}",
                                       headers={"Connection": "close"})
                if length is None:
                    body += chunk
                    if end > ticket.bytes:
                        ticket.charge(end)
                elif end > length:
                    raise ApiError(400, f"the body is longer than its Content-Length of {length} bytes")
                else:
                    body[received:end] = np.frombuffer(chunk, np.uint8)
                received = end
        except ClientDisconnect:
            raise ApiError(400, "client disconnected before sending the whole body") from None
    if received != len(body):
        raise ApiError(400, f"the body ended after {received} of its Content-Length of {length} bytes")
    return memoryview(body)  # not copied again: the tensors are views of it


def _cube(parsed: InferRequest, served: ServedModel) -> tuple[InputKind, np.ndarray]:
    """The one input as the cube /v1/segment would have read (complex from its trailing axis of 2; an ADC
    frame decoded to complex samples in the "sck" layout by service.inputs.adc_upload, as /v1/segment?input=adc
    decodes it), its values checked as /v1/segment checks them."""
    if len(parsed.inputs) != 1:
        raise ProtocolError(400, f"send exactly one input (one of {list(INPUTS)}), got {sorted(parsed.inputs)}")
    ((name, array),) = parsed.inputs.items()
    kind, frames = INPUTS[name], None
    if name in ("complex", "adc"):  # real and imaginary parts on a trailing axis of 2
        array = np.ascontiguousarray(array).view(_COMPLEX[array.dtype])[..., 0]
    if kind is InputKind.adc:
        frames = AdcFrameInput(served.net.profile)
        array = frames.to_sck(array, frames.layout_for(array.dtype, array.shape))
    expected = ExpectedCube(served.spec.name, array.shape, kind, frames)
    check_values(array, expected)
    return kind, array


def _decode(body: memoryview, header_length: str | None, served: ServedModel
            ) -> tuple[InferRequest, InputKind, np.ndarray]:
    parsed = parse_request(body, header_length, _input_shapes(served), OUTPUTS)
    return parsed, *_cube(parsed, served)


def _tensors(billed: Any, name: str) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
    result = billed.result
    objects = np.array([[getattr(o, c) for c in OBJECT_COLUMNS] for o in result.objects], np.float32)
    compute = json.dumps({"request_id": billed.request_id, "model": name, "compute": billed.compute.model_dump(),
                          "usage": billed.usage.model_dump()})
    tensors = {"labels": result.labels, "ra_mask": result.ra_mask, "rd_mask": result.rd_mask,
               "objects": objects.reshape(-1, len(OBJECT_COLUMNS)), "compute": np.array([compute.encode()], object)}
    return tensors, {"objects": {"columns": ",".join(OBJECT_COLUMNS)}}


@router.post("/v2/models/{name}/infer", summary="Segment one cube (Open Inference Protocol)",
             responses=protocol_errors(400, 404, 408, 413, 415, 422, 429, 503))
async def infer(request: Request, state: State, caller: Caller, name: str = ModelName) -> Response:
    """Billed and limited as ``POST /v1/segment``: the model ready and the ledger up, the tenant's quota checked
    before the body is read, the upload gate, the cube's values, a model slot (503 when saturated)."""
    try:
        return await _infer(request, state, caller, name)
    except ApiError as exc:
        return protocol_error(exc.status, exc.message, exc.headers)
    except ProtocolError as exc:
        return protocol_error(exc.status, str(exc))


async def _infer(request: Request, state: ServiceState, caller: Principal, name: str) -> Response:
    served = _served(state, name)
    if state.ledger_error is not None:
        raise ApiError(503, f"usage ledger unavailable ({state.ledger_error}); the request was not billed",
                       headers={"Retry-After": str(state.settings.retry_after_s)})
    _check_media_type(request)
    await state.billing.check(caller.tenant, served)  # a tenant over its quota sends no body for nothing
    started = time.perf_counter()
    body = await _read_body(request, state, caller.tenant, served)
    async with state.request_decoding:  # CPU work of the body's size, off the event loop, a few at a time
        parsed, kind, cube = await run_in_threadpool(_decode, body, request.headers.get(HEADER_LENGTH), served)
    del body
    decode_s = time.perf_counter() - started
    admitted = Admitted({"objects", "masks"}, served, ExpectedCube(served.spec.name, cube.shape, kind), None)
    billed = await run_billed(state, caller, admitted, cube, decode_s, kind, True, MaskEncoding.rle)
    tensors, parameters = _tensors(billed, name)
    chosen = parsed.outputs or tuple(RequestedOutput(output, parsed.binary_output) for output in OUTPUTS)
    payload, header_length = encode_response(name, parsed.id, tensors, parameters, chosen)
    headers = {"X-Request-ID": billed.request_id, "X-Compute-MACs": str(billed.compute.macs.total)}
    if header_length is not None:
        headers[HEADER_LENGTH] = str(header_length)
        return Response(payload, media_type="application/octet-stream", headers=headers)
    return Response(payload, media_type="application/json", headers=headers)


def _unknown_version(name: str, version: str) -> JSONResponse | None:
    if version in VERSIONS:
        return None
    return protocol_error(404, f"model {name!r} has no version {version[:64]!r}: its versions are {list(VERSIONS)}")


@router.get("/v2/models/{name}/versions/{version}", summary="A model version's metadata (Open Inference Protocol)",
            responses=protocol_errors(404, 503))
def version_metadata(state: State, caller: Caller, name: str = ModelName,
                     version: str = ModelVersion) -> JSONResponse:
    return _unknown_version(name, version) or model_metadata(state, caller, name)


@router.get("/v2/models/{name}/versions/{version}/ready", summary="A model version's readiness (Open Inference "
            "Protocol)", responses=protocol_errors(404, 503))
def version_ready(state: State, caller: Caller, name: str = ModelName, version: str = ModelVersion) -> JSONResponse:
    return _unknown_version(name, version) or model_ready(state, caller, name)


@router.post("/v2/models/{name}/versions/{version}/infer", summary="Segment one cube with a model version (Open "
             "Inference Protocol)", responses=protocol_errors(400, 404, 408, 413, 415, 422, 429, 503))
async def version_infer(request: Request, state: State, caller: Caller, name: str = ModelName,
                        version: str = ModelVersion) -> Response:
    """``POST /v2/models/{name}/infer`` for the model's one version, ``1``."""
    return _unknown_version(name, version) or await infer(request, state, caller, name)
