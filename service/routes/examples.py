"""GET /v1/examples and GET /v1/examples/{n}: a few simulated cubes for a served model's preset, made on
demand by the project's simulator with fixed seeds (nothing downloaded, nothing stored in the repository),
so a client such as the viewer has something to segment at once. Each example is simulated once per radar
(single flight, one simulation at a time, kept within ``example_cache_bytes``: :mod:`service.example_cache`) and
not billed; a radar whose classes the simulator does not know has no examples (404 ``no_examples``)."""

from __future__ import annotations

import re
from typing import Annotated
from urllib.parse import quote

from fastapi import APIRouter, Path, Query, Response

from service.deps import Caller, ServiceState, State
from service.example_cache import ExampleSequence, NoExamples
from service.http.errors import ApiError
from service.inference import ServedModel
from service.routes.errors_doc import error_responses
from service.schemas import ErrorBody, ExampleInfo, ExampleObject, ExamplesResponse

router = APIRouter(tags=["examples"])

# Example n is the sequence simulated with EXAMPLE_SEEDS[n - 1]; seeds chosen for scenes that hold every class of
# the small preset between them (seed 2: a car, two cyclists and a pedestrian).
EXAMPLE_SEEDS = (2, 7, 10)
EXAMPLE_FRAMES = 10  # frames of each example's sequence (?frame=K): the viewer plays them as a stream
MIN_VOXELS = 20  # objects with fewer labelled voxels are barely visible; the example's listing leaves them out
UNSAFE_FILENAME = re.compile(r"[^A-Za-z0-9._-]+")

NPY_RESPONSE = {200: {"description": "the example's complex64 RAD cube (R, A, D) as a .npy file",
                      "content": {"application/x-npy": {"schema": {"type": "string", "format": "binary"}}}}}
NOT_FOUND = {404: {"model": ErrorBody, "description": "No example with this number, or none for this radar"}}
ModelName = Annotated[str | None, Query(description="served model whose preset the cubes are made for; the "
                                                    "default model if omitted", max_length=64)]


def attachment(filename: str) -> str:
    """A ``Content-Disposition`` naming ``filename`` safely (RFC 6266): an ASCII slug as ``filename`` (no quote,
    separator or control character) and the name itself percent-encoded as ``filename*``."""
    slug = UNSAFE_FILENAME.sub("_", filename).strip("._") or "example.npy"
    return f"attachment; filename=\"{slug}\"; filename*=UTF-8''{quote(filename.replace('/', '_'), safe='')}"

def _served(state: State, name: str | None) -> ServedModel:
    try:
        served = state.pool.get(name)
    except KeyError as exc:
        raise ApiError(422, exc.args[0], error="unknown_model") from None
    if not served.ready:
        raise ApiError(503, f"model {served.spec.name!r} is not ready: {served.error}", error="not_ready",
                       headers={"Retry-After": str(state.settings.retry_after_s)})
    return served


def _seed(n: int) -> int:
    if not 1 <= n <= len(EXAMPLE_SEEDS):
        raise ApiError(404, f"no example {n}: examples are numbered 1 to {len(EXAMPLE_SEEDS)}")
    return EXAMPLE_SEEDS[n - 1]


def _example(state: ServiceState, served: ServedModel, n: int) -> ExampleSequence:
    """Example ``n`` of the model's radar (simulated once, kept); 404 no_examples for a radar the simulator
    cannot place objects for."""
    try:
        return state.examples.get(served.net.profile, _seed(n))
    except NoExamples as exc:
        raise ApiError(404, f"model {served.spec.name!r} has no examples: {exc}", error="no_examples") from None


def _info(n: int, served: ServedModel, example: ExampleSequence) -> ExampleInfo:
    objects = [ExampleObject(class_name=o.class_name, range_m=round(o.true_range_m, 3),
                             angle_deg=round(o.true_angle_deg, 3), velocity_mps=round(o.true_velocity_mps, 3),
                             n_voxels=o.n_voxels)
               for o in example.objects if o.n_voxels >= MIN_VOXELS]
    return ExampleInfo(n=n, seed=_seed(n), preset=served.net.profile.name, shape=list(example.shape),
                       dtype=example.dtype, url=f"/v1/examples/{n}?model={served.spec.name}", objects=objects,
                       frames=len(example.frames))


@router.get("/v1/examples", response_model=ExamplesResponse, responses=error_responses(401, 404, 422, 503))
def list_examples(state: State, caller: Caller, model: ModelName = None) -> ExamplesResponse:
    """The example cubes for the model's preset: seed, shape, where to fetch each, and the objects the
    simulator placed in it (class, range, angle, radial velocity; those of at least 20 labelled voxels)."""
    served = _served(state, model)
    return ExamplesResponse(model=served.spec.name, examples=[_info(n, served, _example(state, served, n))
                                                              for n in range(1, len(EXAMPLE_SEEDS) + 1)])


@router.get("/v1/examples/{n}", response_class=Response,
            responses={**NPY_RESPONSE, **NOT_FOUND, **error_responses(401, 422, 503)})
def get_example(state: State, caller: Caller, n: Annotated[int, Path(description="example number, from 1")],
                model: ModelName = None,
                frame: Annotated[int, Query(ge=0, lt=EXAMPLE_FRAMES, description="frame of the example's sequence "
                                            "(0: the frame the listing describes)")] = 0) -> Response:
    """Example ``n`` as the .npy bytes ``POST /v1/segment`` takes (complex64 RAD cube of the model's preset); with
    ``frame=K``, frame K of its sequence (what ``POST /v1/streams/{id}/frames`` takes in order)."""
    served = _served(state, model)
    seed = _seed(n)
    payload = _example(state, served, n).frames[frame]
    name = f"example-{n}-{served.net.profile.name}{f'-frame-{frame}' if frame else ''}.npy"
    return Response(payload, media_type="application/x-npy",
                    headers={"Content-Disposition": attachment(name), "X-Example-Seed": str(seed)})
