"""A served model's radar, checked before its networks are built or warmed up: the profile its checkpoints carry
(bounded by radar.profiles.limits: sizes, finite numbers, the tracker's configuration) and the cube a client must
send for it, which must fit the service's body limit. A model refused here is reported (``/readyz``,
``GET /v1/models``) as not loaded with the one line saying why; the service keeps serving the others."""

from __future__ import annotations

import numpy as np

from models.checkpoint import load_checkpoint
from radar.errors import UserError
from radar.tracking import TrackerConfig
from service.settings import ModelSpec, Settings, resolve_path

NPY_HEADER_BYTES = 128  # what np.save writes before the data of a 3-axis cube (v1 header)


def radar_refusal(spec: ModelSpec, settings: Settings) -> str | None:
    """Why ``spec``'s radar cannot be served (None when it can): its detector checkpoint's profile is out of
    bounds, its tracker configuration does not build, or its complex64 cube does not fit ``max_body_bytes``. A
    checkpoint that does not load is left to the model's own loading, which reports it."""
    try:
        profile = load_checkpoint(resolve_path(spec.detector)).profile
    except UserError as exc:
        return None if "no such checkpoint" in str(exc) or "not a checkpoint" in str(exc) else str(exc)
    try:  # a stream's every frame builds it: a bad one refuses the model now, not each frame with a 500
        TrackerConfig.for_profile(profile)
    except (ValueError, TypeError) as exc:
        return f"model {spec.name!r}: its radar's tracker configuration is refused: {exc}"
    body = NPY_HEADER_BYTES + int(np.prod(profile.shape)) * np.dtype(np.complex64).itemsize
    if body > settings.max_body_bytes:
        return (f"model {spec.name!r}: its radar's cube {profile.shape} is a {body}-byte complex64 body, more than "
                f"max_body_bytes ({settings.max_body_bytes}); raise RADARSEG_MAX_BODY_BYTES or serve a smaller radar")
    return None
