"""GET /v1/examples and GET /v1/examples/{n}: a few simulated cubes for a served model's preset, made on
demand by the project's simulator with fixed seeds (nothing downloaded, nothing stored in the repository),
so a client such as the viewer has something to segment at once."""

from __future__ import annotations

import io
from functools import lru_cache
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Path, Query, Response

from radar.frame import RadarFrame
from radar.profiles import RadarProfile
from radar.simulate import simulate_sequence
from service.deps import Caller, State
from service.errors import ApiError
from service.inference import ServedModel
from service.routes.errors_doc import error_responses
from service.schemas import ErrorBody, ExampleInfo, ExampleObject, ExamplesResponse

router = APIRouter(tags=["examples"])

# Example n is the first frame of the sequence simulated with EXAMPLE_SEEDS[n - 1]; seeds chosen for scenes
# that hold every class of the small preset between them (seed 2: a car, two cyclists and a pedestrian).
EXAMPLE_SEEDS = (2, 7, 10)
EXAMPLE_FRAMES = 10  # frames of each example's sequence (?frame=K): the viewer plays them as a stream
MIN_VOXELS = 20  # objects with fewer labelled voxels are barely visible; the example's listing leaves them out

NPY_RESPONSE = {200: {"description": "the example's complex64 RAD cube (R, A, D) as a .npy file",
                      "content": {"application/x-npy": {"schema": {"type": "string", "format": "binary"}}}}}
NOT_FOUND = {404: {"model": ErrorBody, "description": "No example with this number"}}
ModelName = Annotated[str | None, Query(description="served model whose preset the cubes are made for; the "
                                                    "default model if omitted", max_length=64)]


@lru_cache(maxsize=2 * len(EXAMPLE_SEEDS))
def example_frame(profile: RadarProfile, seed: int) -> RadarFrame:
    """The first frame of the sequence simulated for ``profile`` with ``seed`` (about 0.2 s for ``small``)."""
    return next(simulate_sequence(profile, 1, seed=seed))


@lru_cache(maxsize=2)  # two sequences' cubes: 80 MB at ``small``
def example_cubes(profile: RadarProfile, seed: int) -> tuple[bytes, ...]:
    """The .npy bytes of every frame of the example sequence (frame 0 equals :func:`example_frame`'s)."""
    cubes = []
    for frame in simulate_sequence(profile, EXAMPLE_FRAMES, seed=seed):
        buffer = io.BytesIO()
        np.save(buffer, frame.cube)
        cubes.append(buffer.getvalue())
    return tuple(cubes)


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


def _info(n: int, served: ServedModel) -> ExampleInfo:
    profile = served.net.profile
    frame = example_frame(profile, _seed(n))
    objects = [ExampleObject(class_name=o.class_name, range_m=round(o.true_range_m, 3),
                             angle_deg=round(o.true_angle_deg, 3), velocity_mps=round(o.true_velocity_mps, 3),
                             n_voxels=o.n_voxels)
               for o in frame.objects if o.n_voxels >= MIN_VOXELS]
    return ExampleInfo(n=n, seed=_seed(n), preset=profile.name, shape=list(frame.cube.shape),
                       dtype=frame.cube.dtype.name, url=f"/v1/examples/{n}?model={served.spec.name}", objects=objects,
                       frames=EXAMPLE_FRAMES)


@router.get("/v1/examples", response_model=ExamplesResponse, responses=error_responses(401, 422, 503))
def list_examples(state: State, caller: Caller, model: ModelName = None) -> ExamplesResponse:
    """The example cubes for the model's preset: seed, shape, where to fetch each, and the objects the
    simulator placed in it (class, range, angle, radial velocity; those of at least 20 labelled voxels)."""
    served = _served(state, model)
    return ExamplesResponse(model=served.spec.name,
                            examples=[_info(n, served) for n in range(1, len(EXAMPLE_SEEDS) + 1)])


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
    if frame == 0:
        buffer = io.BytesIO()
        np.save(buffer, example_frame(served.net.profile, seed).cube)
        payload = buffer.getvalue()
    else:
        payload = example_cubes(served.net.profile, seed)[frame]
    name = f"example-{n}-{served.net.profile.name}{f'-frame-{frame}' if frame else ''}.npy"
    return Response(payload, media_type="application/x-npy",
                    headers={"Content-Disposition": f'attachment; filename="{name}"', "X-Example-Seed": str(seed)})
