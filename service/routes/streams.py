"""Streams: a radar's frames in order, segmented as by POST /v1/segment and tracked across frames (radar.tracking).

``POST /v1/streams`` opens one (201 ``{"id": ...}``), ``POST /v1/streams/{id}/frames?seq=N`` takes a cube and
answers the /v1/segment answer with each object's ``track_id`` and velocity vector and the stream's tracks,
``GET /v1/streams/{id}`` shows it, ``DELETE /v1/streams/{id}`` closes it. The tracker's state lives in the ledger's
database (:mod:`service.streams.store`): any replica serves the next frame, and one restarted mid-stream loses no
track. A frame is billed as a /v1/segment request, once its tracks are written: a frame whose stream was closed
(DELETE) while it ran is a 404 ``stream_closed`` and one whose hold was taken by another frame a 409
``stream_claim_lost``, neither billed; every billed answer carries its compute and request id.

Order: ``seq`` must be after the stream's last frame (a repeated or older one is a 409); a gap of ``k`` frames is
coasted (every track predicted over ``k`` frame periods). Two frames of one stream never run at once: the second
is a 409 with Retry-After while the first holds the stream, and the first's hold is renewed while it runs.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from radar.track_priors import TrackPriors, TrackPriorsConfig
from radar.tracking import Measurements, Track, Tracker, TrackerConfig, TrackerStep, TrackStatus
from service.accounting.ledger import utc_now
from service.deps import Caller, ServiceState, State
from service.http.errors import ApiError
from service.inputs.json_body import json_request_body, read_json
from service.routes.errors_doc import error_responses
from service.routes.segment import REQUEST_BODY, admit, read_body, respond, run_billed
from service.schemas import (
    InputKind,
    MaskEncoding,
    StreamCreate,
    StreamFrameResponse,
    StreamInfo,
    TrackedObjectOut,
    TrackOut,
)
from service.streams.recording import RecordingFormat, record_frame, recording_bytes
from service.streams.store import Claim, Refusal, StreamRow

router = APIRouter(tags=["streams"])

StreamId = Annotated[str, Path(pattern=r"^[0-9a-f]{32}$", description="the id POST /v1/streams answered")]


def _refused(refusal: Refusal, state: ServiceState, stream_id: str, seq: int | None = None,
             frees_in_s: float = 0.0) -> ApiError:
    retry = {"Retry-After": str(state.settings.retry_after_s)}
    return {
        Refusal.missing: lambda: ApiError(404, f"no stream {stream_id!r} for this tenant (never opened, or closed)"),
        Refusal.expired: lambda: ApiError(404, f"stream {stream_id!r} expired: no frame for "
                                               f"{state.settings.stream_idle_s:g} s (stream_idle_s)",
                                          error="stream_expired"),
        Refusal.busy: lambda: ApiError(409, f"another frame of stream {stream_id!r} is in flight; frames of a stream "
                                            "run one at a time", error="stream_busy", headers=retry),
        Refusal.stale: lambda: ApiError(409, f"frame seq={seq} is not after the stream's last frame; send frames in "
                                             "order with increasing ?seq=", error="stream_order"),
        Refusal.too_many: lambda: ApiError(429, f"the tenant holds {state.settings.max_streams_per_tenant} open "
                                                "streams (max_streams_per_tenant): close one (DELETE) or let one "
                                                f"expire (the first expires in {frees_in_s:.0f} s)",
                                           error="too_many_streams",
                                           headers={"Retry-After": str(max(1, int(frees_in_s) + 1))}),
        Refusal.closed: lambda: ApiError(404, f"stream {stream_id!r} was closed (DELETE) while frame seq={seq} ran; "
                                              "the frame was not billed and its tracks were not kept",
                                         error="stream_closed"),
        Refusal.lost: lambda: ApiError(409, f"frame seq={seq} of stream {stream_id!r} lost its hold on the stream "
                                            "to another frame; it was not billed and its tracks were not kept",
                                       error="stream_claim_lost"),
    }[refusal]()


def _tracker_config(state: ServiceState, model: str) -> TrackerConfig:
    return TrackerConfig.for_profile(state.pool.get(model).net.profile)


def _track_out(summary: dict[str, Any], class_names: tuple[str, ...]) -> TrackOut:
    class_id = summary["class_id"]
    name = class_names[class_id] if 0 <= class_id < len(class_names) else str(class_id)
    return TrackOut(class_name=name, **summary)


def _info(stream: StreamRow, state: ServiceState, kept: list[Track] | None = None) -> StreamInfo:
    """The stream as answered; ``kept``: its tracks when the caller has them (else read from its stored state)."""
    served = state.pool.models.get(stream.model)
    names = served.net.class_names if served is not None and served.ready else ()
    if kept is None:
        kept = [] if stream.state is None else [Track.from_state(t) for t in stream.state["tracks"]]
    tracks = [_track_out(t.summary(), names) for t in kept if t.status is not TrackStatus.tentative]
    return StreamInfo(id=stream.id, model=stream.model, created_at=stream.created_at.isoformat(),
                      updated_at=stream.updated_at.isoformat(),
                      expires_at=stream.expires_at(state.settings.stream_idle_s).isoformat(),
                      last_seq=stream.last_seq, frames=stream.frames, tracks=tracks)


@router.post("/v1/streams", status_code=201, response_model=StreamInfo, summary="Open a stream of frames",
             responses=error_responses(401, 413, 415, 422, 429, 503),
             openapi_extra=json_request_body(StreamCreate, "optional: the served model of the stream"))
async def create_stream(request: Request, state: State, caller: Caller) -> StreamInfo:
    """A new stream on ``model`` (the default model if omitted); its frames are tracked together. At most
    ``max_streams_per_tenant`` live streams per tenant (429 beyond, Retry-After until the first expires). The JSON
    body is read only once the key is checked, and is at most ``max_json_body_bytes`` (413 beyond)."""
    body = await read_json(request, state.settings, state.uploads, caller.tenant, StreamCreate)
    try:
        served = state.pool.get(None if body is None else body.model)
    except KeyError as exc:
        raise ApiError(422, exc.args[0], error="unknown_model") from None
    stream = await state.billing.read(state.streams.create, caller.tenant, served.spec.name)
    if stream is Refusal.too_many:
        raise _refused(stream, state, "", frees_in_s=await state.billing.read(state.streams.next_free_in,
                                                                              caller.tenant))
    if isinstance(stream, Refusal):
        raise _refused(stream, state, "")
    return _info(stream, state)


@router.get("/v1/streams/{stream_id}", response_model=StreamInfo, summary="A stream and its tracks",
            responses=error_responses(401, 404, 503))
async def get_stream(stream_id: StreamId, state: State, caller: Caller) -> StreamInfo:
    stream = await state.billing.read(state.streams.get, caller.tenant, stream_id)
    if isinstance(stream, Refusal):
        raise _refused(stream, state, stream_id)
    return _info(stream, state)


@router.delete("/v1/streams/{stream_id}", status_code=204, summary="Close a stream",
               responses=error_responses(401, 404, 503))
async def delete_stream(stream_id: StreamId, state: State, caller: Caller) -> Response:
    if not await state.billing.read(state.streams.delete, caller.tenant, stream_id):
        raise _refused(Refusal.missing, state, stream_id)
    state.stream_history.forget((caller.tenant, stream_id))
    state.stream_recordings.forget((caller.tenant, stream_id))
    return Response(status_code=204)


@router.get("/v1/streams/{stream_id}/recording", summary="A stream's recording (MCAP, ROS 2 MCAP or Rerun .rrd)",
            responses={**error_responses(401, 404, 503), 200: {"content": {"application/x-mcap": {},
                                                                            "application/x-rerun-rrd": {}}}})
async def stream_recording(stream_id: StreamId, state: State, caller: Caller,
                           form: Annotated[RecordingFormat, Query(alias="format", description="mcap (Foxglove's "
                                           "schemas), ros2 (ROS 2 messages in MCAP) or rrd (Rerun)")]
                           = RecordingFormat.mcap) -> Response:
    """The frames of the stream this replica segmented, as a recording: points, objects with track ids and
    velocity arrows, RA / RD label maps, each frame at ``seq`` frame periods (service/streams/recording.py)."""
    stream = await state.billing.read(state.streams.get, caller.tenant, stream_id)
    if isinstance(stream, Refusal):
        raise _refused(stream, state, stream_id)
    kept = state.stream_recordings.frames((caller.tenant, stream_id))
    if kept is None:
        raise ApiError(404, f"no frame of stream {stream_id!r} was segmented by this replica (or its recording was "
                            "evicted for memory)", error="no_recording")
    payload = await run_in_threadpool(recording_bytes, *kept, form)
    return Response(payload, media_type=form.media_type, headers={
        "Content-Disposition": f'attachment; filename="stream-{stream_id}{form.suffix}"'})


def _priors(claim: Claim, state: ServiceState) -> TrackPriors | None:
    """Where the stream's confirmed tracks expect their objects in this frame, if the service seeds from them
    (``stream_track_priors``) and the stream has tracks."""
    threshold = state.settings.stream_track_priors
    if threshold is None or claim.stream.state is None:
        return None
    tracker = Tracker.from_state(_tracker_config(state, claim.stream.model), claim.stream.state)
    return TrackPriors(tracker.predicted_positions(frames=claim.gap), TrackPriorsConfig(threshold))


def _track(claim: Claim, result_objects: list[Any], state: ServiceState) -> tuple[Tracker, TrackerStep]:
    """The stream's tracker after this frame (the gap since its last frame coasted)."""
    config = _tracker_config(state, claim.stream.model)
    tracker = (Tracker(config) if claim.stream.state is None
               else Tracker.from_state(config, claim.stream.state))
    return tracker, tracker.step(Measurements.from_objects(result_objects), frames=claim.gap)


@router.post("/v1/streams/{stream_id}/frames", response_model=StreamFrameResponse, summary="Segment and track a frame",
             responses=error_responses(400, 401, 404, 408, 409, 413, 415, 422, 429, 503), openapi_extra=REQUEST_BODY)
async def stream_frame(
    request: Request,
    stream_id: StreamId,
    state: State,
    caller: Caller,
    seq: Annotated[int, Query(ge=0, le=2**62, description="the frame's number in the stream: after the last one; "
                                                          "a gap is coasted")],
    input_kind: Annotated[InputKind, Query(alias="input", description="what the cube holds")] = InputKind.complex,
    outputs: Annotated[str, Query(description="as for POST /v1/segment", max_length=64)] = "objects,masks",
    encoding: Annotated[MaskEncoding, Query(description="encoding of masks and voxels")] = MaskEncoding.rle,
    tdm_compensation: Annotated[bool, Query(description="?input=adc: compensate TDM Doppler-angle coupling")] = True,
    cube_schema: Annotated[str | None, Header(alias="X-Cube-Schema", max_length=8192,
                                              description="as for POST /v1/segment")] = None,
) -> Response:
    """The /v1/segment answer for this frame (billed as one), each object with its ``track_id``, ``vx`` and ``vy``,
    and the stream after the frame with its confirmed and coasted tracks. Checked before the body is read: the
    stream (404), the order (409), then everything /v1/segment checks."""
    store = state.streams
    stream = await state.billing.read(store.check, caller.tenant, stream_id, seq)
    if isinstance(stream, Refusal):
        raise _refused(stream, state, stream_id, seq)
    admitted = await admit(request, state, caller, stream.model, input_kind, outputs, cube_schema)
    cube, decode_s = await read_body(request, state, caller, admitted)
    claim = await state.billing.read(store.claim, caller.tenant, stream_id, seq)
    if isinstance(claim, Refusal):
        raise _refused(claim, state, stream_id, seq)
    n_history = admitted.served.net.history_frames
    history = state.stream_history.earlier((caller.tenant, stream_id), seq, n_history) if n_history else None
    kept: dict[str, Any] = {}

    async def keep(result: Any) -> None:
        """The tracks after this frame, written under the claim before the frame is billed: a stream closed or
        taken meanwhile refuses the frame unbilled."""
        start = time.perf_counter()
        tracker, step = _track(claim, result.objects, state)
        kept.update(tracker=tracker, step=step, track_s=time.perf_counter() - start, state=tracker.to_state())
        refused = await state.billing.read(store.commit, claim, kept["state"])
        if refused is not None:
            raise _refused(refused, state, stream_id, seq)
        kept["committed"] = True

    async with _holding(state, claim, kept):
        billed = await run_billed(state, caller, admitted, cube, decode_s, input_kind, tdm_compensation, encoding,
                                  history, keep=keep, priors=_priors(claim, state))
    tracker, step, track_s, tracker_state = kept["tracker"], kept["step"], kept["track_s"], kept["state"]
    if n_history:  # what the stream's next frame reads
        state.stream_history.keep((caller.tenant, stream_id), seq, billed.result.log_power, n_history)
    state.metrics.stage_seconds.labels(admitted.name, "track").observe(track_s)
    record_frame(state.stream_recordings, (caller.tenant, stream_id), admitted.served.net, seq, billed.result,
                 step.object_tracks)
    row = StreamRow(claim.stream.id, claim.stream.tenant, claim.stream.model, claim.stream.created_at,
                    utc_now(), seq, claim.stream.frames + 1, tracker_state)
    net = admitted.served.net
    objects = [TrackedObjectOut(**obj.to_dict(), track_id=track.id, vx=float(track.mean[2]), vy=float(track.mean[3]))
               for obj, track in zip(billed.result.objects, step.object_tracks, strict=True)]
    body = StreamFrameResponse(request_id=billed.request_id, model=admitted.name, preset=net.profile.name,
                               shape=list(net.profile.shape), class_names=list(net.class_names), views=billed.views,
                               compute=billed.compute, usage=billed.usage, seq=seq,
                               stream=_info(row, state, tracker.tracks),
                               history_frames=sum(frame is not None for frame in history or ()),
                               prior_seeds=billed.result.prior_seeds)
    response = await respond(body, billed, admitted, encoding, state, caller, objects)
    response.headers["X-Stream-Id"] = stream_id
    return response


async def _release(state: ServiceState, claim: Claim) -> None:
    """Give the stream back after a frame that failed (a failure to do so leaves the claim to expire)."""
    try:
        await state.billing.read(state.streams.release, claim)
    except ApiError:
        pass


async def _renew(state: ServiceState, claim: Claim) -> None:
    """Keep the claim live while its frame runs (a frame waiting for a model slot or running long never loses its
    stream to the next one); stops when the claim is lost or the ledger fails."""
    every = state.settings.stream_claim_s / 3
    while True:
        await asyncio.sleep(every)
        try:
            if not await state.billing.read(state.streams.extend, claim):
                return
        except ApiError:
            return


@contextlib.asynccontextmanager
async def _holding(state: ServiceState, claim: Claim, kept: dict[str, Any]) -> Any:
    """Renew ``claim`` while the block runs; give the stream back after unless the frame committed."""
    renewing = asyncio.create_task(_renew(state, claim), name="radarseg-stream-claim")
    try:
        yield
    finally:
        renewing.cancel()
        if not kept.get("committed"):
            await _release(state, claim)

