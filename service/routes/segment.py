"""POST /v1/segment: a .npy RAD cube in, objects, masks, voxels and the request's compute figures out."""

from __future__ import annotations

import time
import uuid
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import BaseModel
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from models.erasenet.compute_report import FrameCompute
from models.erasenet.model import SegmentationResult
from radar.adc import adc_shape
from radar.input_kind import SCHEMA_CONTENT
from radar.schema import SchemaMismatch, check_schema
from radar.track_priors import TrackPriors
from service.accounting.tenants import Principal
from service.deps import Caller, ServiceState, State
from service.encoding import encode_array
from service.http.errors import ApiError
from service.inference import NotReady, Saturated, ServedModel
from service.input_views import input_views
from service.inputs.adc_upload import AdcFrameInput
from service.inputs.capture_upload import read_capture_body
from service.inputs.json_body import declared_length
from service.inputs.json_header import load_json_header
from service.inputs.upload import ExpectedCube, check_declared_length, paced, read_cube
from service.routes.errors_doc import error_responses
from service.schemas import (
    Compute,
    InputKind,
    InputViews,
    MaskEncoding,
    ObjectOut,
    RequestUsage,
    SegmentResponse,
    VoxelsOut,
)

router = APIRouter(tags=["segmentation"])

CONTENT_TYPES = ("application/x-npy", "application/octet-stream")
OUTPUTS = ("objects", "masks", "voxels", "views")
_BINARY = {"schema": {"type": "string", "format": "binary"}}
REQUEST_BODY = {
    "requestBody": {
        "required": True,
        "description": "A .npy file: the complex RAD cube (R, A, D) of the model's preset (complex64/complex128), "
                       "its linear magnitude with ?input=magnitude or its log power in dB with ?input=log_power "
                       "(float16/32/64), or raw ADC samples with ?input=adc (one frame, complex or int16 with I/Q "
                       "on a trailing axis of 2, layout ti or sck; or with ?format=dca1000 a DCA1000 capture's "
                       "bytes). Pickled arrays are refused.",
        "content": {content_type: _BINARY for content_type in CONTENT_TYPES},
    }
}


def _parse_outputs(outputs: str) -> set[str]:
    chosen = {part.strip() for part in outputs.split(",") if part.strip()}
    if unknown := sorted(chosen - set(OUTPUTS)):
        raise ApiError(422, f"unknown outputs {unknown}; choose among {list(OUTPUTS)} (comma-separated)",
                       error="invalid_parameters")
    return chosen


def _check_content_type(request: Request) -> None:
    media_type = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if media_type not in CONTENT_TYPES:
        raise ApiError(415, f"content type {media_type or '(none)'!r} is not accepted: send the .npy bytes as "
                            f"{' or '.join(CONTENT_TYPES)}")


def _served_model(state: ServiceState, name: str | None) -> ServedModel:
    try:
        served = state.pool.get(name)
    except KeyError as exc:
        raise ApiError(422, exc.args[0], error="unknown_model") from None
    retry = {"Retry-After": str(state.settings.retry_after_s)}
    if not served.ready:
        raise ApiError(503, f"model {served.spec.name!r} is not ready ({served.stage}): {served.error}",
                       error="not_ready", headers=retry)
    if state.ledger_error is not None:
        raise ApiError(503, f"usage ledger unavailable ({state.ledger_error}); the request was not billed",
                       error="ledger_unavailable", headers=retry)
    return served


def _compute(report: FrameCompute) -> Compute:
    """The response's compute block of the request's report (its seconds rounded to the microsecond)."""
    return Compute(macs=report.macs_by_stage(), params=report.params_by_network(),
                   seconds=report.seconds_by_stage(decimals=6), roi_voxels=report.roi_voxels,
                   visited_points=report.visited_points, detections=report.detections, runtime=report.runtime,
                   engine=report.runtime)


def _check_cube_schema(header: str, served: ServedModel, input_kind: InputKind, max_depth: int) -> None:
    """400 for JSON nested too deep or invalid, 422 naming every difference between the client's cube schema and
    the model's (radar.schema)."""
    given = load_json_header("X-Cube-Schema", header, max_depth=max_depth)
    content = SCHEMA_CONTENT[input_kind]
    try:
        check_schema(served.net.schema(content), given, what="cube")
    except SchemaMismatch as exc:
        raise ApiError(422, str(exc), error="schema_mismatch") from None


def _encode(body: SegmentResponse, result: SegmentationResult, outputs: set[str], encoding: MaskEncoding,
            objects: list[BaseModel] | None = None) -> bytes:
    """Fill the chosen outputs and serialise (runs on a worker thread: masks and voxels can be large).
    ``objects``: the objects as answered (default: ``ObjectOut`` of the result's)."""
    if "objects" in outputs:
        body.objects = objects if objects is not None else [ObjectOut(**obj.to_dict()) for obj in result.objects]
    if "masks" in outputs:
        body.ra_mask = encode_array(result.ra_mask, encoding)
        body.rd_mask = encode_array(result.rd_mask, encoding)
    if "voxels" in outputs:
        voxels = result.regions.voxels
        classes = result.labels[tuple(voxels.T)] if len(voxels) else np.zeros(0, np.uint8)
        keep = classes > 0
        table = np.column_stack([voxels[keep], classes[keep]]).astype(np.uint16).reshape(-1, 4)
        body.voxels = VoxelsOut(count=len(table), array=encode_array(table, encoding))
    return body.model_dump_json(exclude_none=True).encode()


def _headers(request_id: str, model: str, tenant: str, compute: Compute, encode_s: float) -> dict[str, str]:
    timings = compute.seconds.model_dump()
    timings.pop("total")
    server_timing = ", ".join(f"{name};dur={seconds * 1e3:.3f}" for name, seconds in
                              [*timings.items(), ("encode", encode_s)])
    return {
        "X-Request-ID": request_id, "X-Model": model, "X-Tenant": tenant,
        "X-Compute-MACs": str(compute.macs.total), "X-Compute-MACs-Detect": str(compute.macs.detect),
        "X-Compute-MACs-Segment": str(compute.macs.segment), "X-Compute-Params": str(compute.params.total),
        "X-Compute-Seconds": f"{compute.seconds.total:.6f}", "X-ROI-Voxels": str(compute.roi_voxels),
        "X-Visited-Points": str(compute.visited_points), "Server-Timing": server_timing,
    }


async def _read_body(request: Request, state: ServiceState, tenant: str, expected: ExpectedCube,
                     content_length: int | None) -> tuple[np.ndarray, float]:
    """The checked cube and the seconds spent receiving and decoding it (before any model slot is taken)."""
    start = time.perf_counter()
    with state.uploads.admit(tenant, content_length) as ticket:
        try:
            cube = await read_cube(paced(request.stream(), state.settings), expected, content_length=content_length,
                                   ticket=ticket)
        except ClientDisconnect:
            raise ApiError(400, "client disconnected before sending the whole body") from None
    return cube, time.perf_counter() - start


def _take_slot(served: ServedModel, state: ServiceState) -> None:
    """A slot of the model (released by the model when the inference ends); 503 when every slot is taken."""
    try:
        served.acquire()
    except Saturated as exc:
        state.metrics.rejected.labels(served.spec.name, "saturated").inc()
        raise ApiError(503, f"{exc}; try again later", error="saturated",
                       headers={"Retry-After": str(state.settings.retry_after_s)}) from None
    state.metrics.queue.labels(served.spec.name).set(served.held)


async def _infer(served: ServedModel, cube: np.ndarray, input_kind: InputKind, tdm_compensation: bool,
                 state: ServiceState, *, views: bool, history: list[np.ndarray | None] | None = None,
                 priors: TrackPriors | None = None) -> SegmentationResult:
    """Inference in the slot taken by :func:`_take_slot` (the model releases it when inference ends)."""
    try:
        return await served.run(cube, kind=input_kind, tdm_compensation=tdm_compensation,
                                views=views, history=history, priors=priors)
    except NotReady as exc:
        raise ApiError(503, str(exc), error="not_ready",
                       headers={"Retry-After": str(state.settings.retry_after_s)}) from None
    finally:
        state.metrics.queue.labels(served.spec.name).set(served.held)


SEGMENT_DOC = dict(
    response_model=SegmentResponse,
    responses=error_responses(400, 401, 408, 413, 415, 422, 429, 503),
    openapi_extra=REQUEST_BODY,
)


@router.post("/v1/segment", summary="Segment one RAD cube", **SEGMENT_DOC)
@router.post("/segment", summary="Segment one RAD cube (alias of POST /v1/segment, the product card's path)",
             operation_id="segment_alias", **SEGMENT_DOC)
async def segment(
    request: Request,
    state: State,
    caller: Caller,
    model: Annotated[str | None, Query(description="served model name (GET /v1/models); default model if omitted",
                                       max_length=64)] = None,
    input_kind: Annotated[InputKind, Query(alias="input", description="what the cube holds")] = InputKind.complex,
    outputs: Annotated[str, Query(description="comma-separated among objects, masks, voxels, views "
                                              "(the RA/RD views of the input: uint8, dB range, bin values)",
                                  max_length=64)] = "objects,masks",
    encoding: Annotated[MaskEncoding, Query(description="encoding of masks and voxels")] = MaskEncoding.rle,
    tdm_compensation: Annotated[bool, Query(description="?input=adc: compensate TDM Doppler-angle coupling")] = True,
    cube_schema: Annotated[str | None, Header(alias="X-Cube-Schema", max_length=8192,
                                              description="the cube's radar.schema description (JSON); a "
                                                          "mismatch with the model's is a 422 naming it")] = None,
    layout: Annotated[Literal["sck", "ti"] | None, Query(
        description="?input=adc: the frame's layout, sck (samples, chirps, virtual elements) or ti (chirps, rx, "
                    "samples); by its shape if omitted")] = None,
    body_format: Annotated[Literal["npy", "dca1000"], Query(
        alias="format", description="the body: npy (a .npy array), or with ?input=adc dca1000 (a DCA1000 capture's "
                                    "bytes, adc_data.bin, read with the model's radar profile)")] = "npy",
    frame: Annotated[int, Query(ge=0, le=2**31, description="?format=dca1000: the capture's frame to segment, "
                                                            "from 0 (the answer's X-Capture-Frames says how many "
                                                            "it holds)")] = 0,
) -> Response:
    """Objects, RA/RD masks and optionally the labelled RAD voxels of one cube, with the request's MACs per
    stage, parameters, latency per stage, ROI voxels and visited points (also in ``X-Compute-*`` and
    ``Server-Timing`` headers), and the tenant's running totals for the day.

    A declared length no cube of the model can have is refused at once (413), and so is a tenant whose quota
    cannot cover the request (429), before the body is read. The body is read next (a slow upload holds no model
    slot), then the request takes a model slot and a lease on the tenant's quota, runs, and is billed; the lease is
    given back on any other way out."""
    capture = body_format == "dca1000"
    admitted = await admit(request, state, caller, model, input_kind, outputs, cube_schema, layout=layout,
                           capture=capture)
    if capture:
        taken, decode_s = await read_capture_body(request, state.uploads, state.settings, caller.tenant,
                                                  admitted.expected, admitted.content_length, frame)
        cube = taken.adc
    else:
        cube, decode_s = await read_body(request, state, caller, admitted)
    billed = await run_billed(state, caller, admitted, cube, decode_s, input_kind, tdm_compensation, encoding)
    net = admitted.served.net
    body = SegmentResponse(request_id=billed.request_id, model=admitted.name, preset=net.profile.name,
                           shape=list(net.profile.shape), class_names=list(net.class_names), views=billed.views,
                           compute=billed.compute, usage=billed.usage)
    response = await respond(body, billed, admitted, encoding, state, caller)
    if capture:
        response.headers.update({"X-Capture-Frames": str(taken.frames), "X-Capture-Frame": str(taken.index)})
    return response


@dataclass
class Admitted:
    """A request checked before its body is read: the outputs it asks for, the model, what cube it must send."""

    chosen: set[str]
    served: ServedModel
    expected: ExpectedCube
    content_length: int | None

    @property
    def name(self) -> str:
        return self.served.spec.name


@dataclass
class Billed:
    """One cube segmented and billed: the result, the request's compute block, its id and the tenant's usage."""

    result: SegmentationResult
    compute: Compute
    request_id: str
    usage: RequestUsage
    views: InputViews | None


async def admit(request: Request, state: ServiceState, caller: Principal, model: str | None, input_kind: InputKind,
                outputs: str, cube_schema: str | None, *, layout: str | None = None,
                capture: bool = False) -> Admitted:
    """Every check made before the body is read: outputs, content type and length, the model (ready, ledger up),
    the cube schema, a length no cube of the model can have (413) and the tenant's quota (429). ``layout``: an ADC
    frame's layout (None: by shape); ``capture``: the body is a DCA1000 capture (?input=adc only)."""
    if (capture or layout is not None) and input_kind is not InputKind.adc:
        raise ApiError(422, f"?{'format=dca1000' if capture else 'layout='} is for ADC samples: send them with "
                            f"?input=adc, not ?input={input_kind.value}", error="invalid_parameters")
    if capture and layout is not None:
        raise ApiError(422, f"?layout={layout} is for one ADC frame sent as .npy: a DCA1000 capture's words are laid "
                            "out as the radar's profile says; leave ?layout= out",
                       error="invalid_parameters")
    chosen = _parse_outputs(outputs)
    _check_content_type(request)
    content_length = declared_length(request)
    served = _served_model(state, model)
    if cube_schema is not None:
        _check_cube_schema(cube_schema, served, input_kind, state.settings.max_json_depth)
    profile = served.net.profile
    accepted = {kind: ExpectedCube(served.spec.name, adc_shape(profile) if kind is InputKind.adc else profile.shape,
                                   kind, AdcFrameInput(profile, layout) if kind is InputKind.adc else None)
                for kind in InputKind}
    if not capture:  # a capture of several frames is bounded by max_body_bytes alone
        check_declared_length(content_length, list(accepted.values()))
    await state.billing.check(caller.tenant, served)  # a tenant over its quota sends no body for nothing
    return Admitted(chosen, served, accepted[input_kind], content_length)


async def read_body(request: Request, state: ServiceState, caller: Principal,
                    admitted: Admitted) -> tuple[np.ndarray, float]:
    """The checked cube and the seconds spent receiving and decoding it (before any model slot is taken)."""
    return await _read_body(request, state, caller.tenant, admitted.expected, admitted.content_length)


async def run_billed(state: ServiceState, caller: Principal, admitted: Admitted, cube: np.ndarray, decode_s: float,
                     input_kind: InputKind, tdm_compensation: bool, encoding: MaskEncoding,
                     history: list[np.ndarray | None] | None = None,
                     keep: Callable[[SegmentationResult], Awaitable[None]] | None = None,
                     priors: TrackPriors | None = None) -> Billed:
    """Take a model slot and a lease on the tenant's quota, run, bill (the lease given back on any other way out).
    ``history``: a stream frame's earlier frames, for a detector that reads them. ``keep``: called with the result
    before it is billed (a stream frame writes its tracks there); when it raises, nothing is billed. ``priors``: a
    stream frame's tracks' predictions (radar.track_priors)."""
    served, name, metrics = admitted.served, admitted.name, state.metrics
    _take_slot(served, state)  # a saturated model answers 503 before the quota is touched (no ledger round trips)
    # reserved (the slot given back if refused); the lease is given back unless settled
    async with state.billing.hold(caller.tenant, served, on_refused=served.release) as quota:
        # the views come from the model's own log power (ADC processed once), inside the compute that is billed
        result = await _infer(served, cube, input_kind, tdm_compensation, state, views="views" in admitted.chosen,
                              history=history, priors=priors)
        del cube
        if keep is not None:
            await keep(result)
        views = None if result.views is None else input_views(*result.views, served.net.profile, encoding)
        report = result.compute.plus_seconds("decode", decode_s, first=True)  # the request's cost, decoding included
        compute = _compute(report)
        request_id = uuid.uuid4().hex
        usage = await quota.settle(model=name, compute=report, request_id=request_id)

    metrics.segmentations.labels(name, caller.tenant).inc()
    metrics.macs.labels(name, caller.tenant).inc(compute.macs.total)
    metrics.roi_voxels.labels(name).inc(compute.roi_voxels)
    for stage, seconds in compute.seconds.model_dump().items():
        if stage != "total":
            metrics.stage_seconds.labels(name, stage).observe(seconds)
    return Billed(result, compute, request_id, usage, views)


async def respond(body: SegmentResponse, billed: Billed, admitted: Admitted, encoding: MaskEncoding,
                  state: ServiceState, caller: Principal, objects: list[BaseModel] | None = None) -> Response:
    """The answer: the chosen outputs encoded on a worker thread, the compute headers."""
    start = time.perf_counter()
    payload = await run_in_threadpool(_encode, body, billed.result, admitted.chosen, encoding, objects)
    encode_s = time.perf_counter() - start
    state.metrics.stage_seconds.labels(admitted.name, "encode").observe(encode_s)
    return Response(payload, media_type="application/json",
                    headers=_headers(billed.request_id, admitted.name, caller.tenant, billed.compute, encode_s))
