"""Request and response schemas of the HTTP API (separate from the internal result types)."""

from __future__ import annotations

from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field

from radar.input_kind import InputKind  # what an uploaded cube holds: the CLI's rule too (docs/design.md section 2)

__all__ = ["InputKind"]  # re-exported: the query parameter ?input= takes it


class MaskEncoding(StrEnum):
    """How masks and voxels are encoded in the JSON response."""

    rle = "rle"  # run-length (value, length) pairs over the C-order flattened array
    zlib = "zlib"  # zlib-compressed C-order bytes, base64


class ErrorBody(BaseModel):
    """Every error answer: a machine-readable ``error`` and a ``detail`` saying what was expected."""

    model_config = ConfigDict(extra="allow")

    error: str = Field(examples=["unprocessable"])
    detail: str = Field(examples=["cube has shape (64, 128, 32), model 'small' expects (128, 128, 32)"])


class QuotaErrorBody(ErrorBody):
    """429: the tenant's daily MAC quota does not cover the request."""

    tenant: str
    day: str
    used_macs: int
    limit_macs: int


class ObjectOut(BaseModel):
    """One segmented object: majority class of its voxels, centre in metres and radial velocity."""

    class_id: int
    class_name: str
    score: float = Field(description="detector score of the seed the object grew from")
    range_m: float
    angle_deg: float = Field(description="positive to the right")
    velocity_mps: float = Field(description="radial velocity, positive receding")
    x: float = Field(description="lateral position (m)")
    y: float = Field(description="forward position (m)")
    n_voxels: int


class EncodedArray(BaseModel):
    """An integer array: ``runs`` of (value, length) for ``rle``, ``data`` (base64 of zlib) for ``zlib``."""

    encoding: MaskEncoding
    dtype: str
    shape: list[int]
    data: str | None = None
    runs: list[tuple[int, int]] | None = None


class VoxelsOut(BaseModel):
    """Foreground RAD voxels, one row per voxel: range bin, angle bin, Doppler bin, class id."""

    columns: list[str] = ["range_bin", "angle_bin", "doppler_bin", "class_id"]
    count: int
    array: EncodedArray


class Macs(BaseModel):
    detect: int
    grow: int
    segment: int
    total: int


class Params(BaseModel):
    detector: int
    segmenter: int
    total: int


class StageSeconds(BaseModel):
    """Latency per stage (s); ``total`` is their sum (request decoding included, response encoding not)."""

    decode: float
    transform: float
    detect: float
    grow: float
    segment: float
    project: float
    total: float


class Compute(BaseModel):
    """What one request cost."""

    macs: Macs
    params: Params
    seconds: StageSeconds
    roi_voxels: int
    visited_points: int
    detections: int
    runtime: str = Field("torch", description="what ran the networks: torch, torch-int8 (the int8 sparse kernels), "
                                              "onnx or onnx-int8 (onnxruntime)")
    engine: str = Field("torch", description="the runtime's former name (the same value), kept for clients that "
                                             "read it")


class UsageTotals(BaseModel):
    """A tenant's totals over a period."""

    requests: int
    macs: int
    compute_seconds: float


class DayUsage(UsageTotals):
    day: str


class RequestUsage(DayUsage):
    """The tenant's running totals for the UTC day, after this request, and its quota."""

    tenant: str
    quota_macs: int | None
    remaining_macs: int | None


class ViewAxes(BaseModel):
    """The physical value at the centre of every bin of the views."""

    range_m: list[float]
    angle_deg: list[float] = Field(description="azimuth per angle bin, positive to the right (bins are uniform "
                                               "in sin(azimuth))")
    velocity_mps: list[float] = Field(description="radial velocity per Doppler bin, positive receding")


class InputView(BaseModel):
    """One view of the input quantised to uint8: ``dB = low_db + value * (high_db - low_db) / 255``."""

    low_db: float
    high_db: float
    array: EncodedArray


class InputViews(BaseModel):
    """``?outputs=views``: what a client draws the masks over. ``ra`` (R, A): max log power over Doppler;
    ``rd`` (R, D): log power summed over angle (``radar.transforms.ra_view``/``rd_view``)."""

    ra: InputView
    rd: InputView
    axes: ViewAxes


class SegmentResponse(BaseModel):
    request_id: str
    model: str
    preset: str
    shape: list[int]
    class_names: list[str]
    objects: list[ObjectOut] | None = None
    ra_mask: EncodedArray | None = None
    rd_mask: EncodedArray | None = None
    voxels: VoxelsOut | None = None
    views: InputViews | None = None
    compute: Compute
    usage: RequestUsage


class ModelInfo(BaseModel):
    name: str
    ready: bool
    error: str | None = None
    preset: str | None = None
    shape: list[int] | None = None
    class_names: list[str] | None = None
    params: Params | None = None
    detector_macs: int | None = Field(None, description="detector MACs per frame (the segmenter's depend on the ROI)")
    score_threshold: float
    max_objects: int
    detector_checkpoint: str
    segmenter_checkpoint: str


class ModelsResponse(BaseModel):
    default: str
    models: list[ModelInfo]


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    ready: bool
    status: str = Field("ready", description="ready, loading (models still loading: see progress) or not_ready")
    progress: dict[str, str] = Field(default_factory=dict, description="model name -> its loading stage: waiting, "
                                     "loading checkpoints, warming up, ready or failed")
    models: dict[str, str | None] = Field(description="model name -> null when loaded, else why not")
    ledger: str | None = Field(description="null when the ledger is reachable, else why not")


class HeldQuota(BaseModel):
    """Today's quota reservations (leases) of requests in flight; expired ones were left by requests cut off
    by a crash and are given back at the tenant's next reservation or the next start-up."""

    leases: int
    macs: int
    expired_leases: int
    expired_macs: int
    lease_seconds: float = Field(description="how long a lease is held before it expires")


class TenantUsage(BaseModel):
    tenant: str
    quota_macs: int | None
    today: DayUsage
    held: HeldQuota
    total: UsageTotals
    days: list[DayUsage]


class UsageResponse(BaseModel):
    tenants: list[TenantUsage]


class ExampleObject(BaseModel):
    """An object the simulator placed in an example cube (its truth), in the units of ``ObjectOut``."""

    class_name: str
    range_m: float
    angle_deg: float
    velocity_mps: float
    n_voxels: int = Field(description="labelled RAD voxels of the object")


class ExampleInfo(BaseModel):
    """One example cube: ``GET url`` answers its .npy bytes (complex64 RAD cube)."""

    n: int
    seed: int
    preset: str
    shape: list[int]
    dtype: str
    url: str
    objects: list[ExampleObject]
    frames: int = Field(description="frames of its sequence: GET url&frame=K for K < frames")


class ExamplesResponse(BaseModel):
    model: str
    examples: list[ExampleInfo]


class TrackedObjectOut(ObjectOut):
    """An object of a stream's frame with the track it belongs to and the track's velocity vector."""

    track_id: int
    vx: float = Field(description="lateral velocity of its track (m/s, positive to the right)")
    vy: float = Field(description="forward velocity of its track (m/s, positive away from the radar)")


class TrackOut(BaseModel):
    """One track of a stream (radar.tracking): filtered position and velocity vector, voted class."""

    track_id: int
    class_id: int
    class_name: str
    status: str = Field(description="tentative (fewer than the hits that confirm it), confirmed, or lost (coasted "
                                    "through missed frames)")
    x: float = Field(description="lateral position (m)")
    y: float = Field(description="forward position (m)")
    vx: float = Field(description="m/s")
    vy: float = Field(description="m/s")
    speed: float = Field(description="m/s")
    heading_deg: float = Field(description="direction of motion, degrees from +x (lateral), counter-clockwise")
    age: int = Field(description="frames since the track started")
    hits: int = Field(description="frames with an object assigned")
    misses: int = Field(description="consecutive frames without one")


class StreamInfo(BaseModel):
    """A stream: its model, its last frame and its confirmed (and coasted) tracks."""

    id: str
    model: str
    created_at: str
    updated_at: str
    expires_at: str = Field(description="when the stream expires unless a frame comes before")
    last_seq: int | None = Field(description="the last frame's ?seq= (null before the first frame)")
    frames: int
    tracks: list[TrackOut] = Field(description="confirmed and lost (coasted) tracks")


class StreamCreate(BaseModel):
    """Optional body of POST /v1/streams."""

    model_config = ConfigDict(extra="forbid")

    model: str | None = Field(None, max_length=64, description="served model name; the default model if omitted")


class StreamFrameResponse(SegmentResponse):
    """The /v1/segment answer for a stream's frame: its objects with their ``track_id`` and velocity vector, and
    the stream after the frame."""

    objects: list[TrackedObjectOut] | None = None
    seq: int
    stream: StreamInfo
    history_frames: int = Field(0, description="earlier frames of the stream the model's detector read with this one "
                                               "(0 for a model that reads one cube, the stream's first frame, a gap, "
                                               "or an earlier frame another replica ran)")
    prior_seeds: int = Field(0, description="centres the stream's tracks added where they expected an object the "
                                            "detector scored under its operating score (0 unless the service "
                                            "seeds from tracks: RADARSEG_STREAM_TRACK_PRIORS)")
