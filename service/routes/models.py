"""GET /v1/models: the served models, their presets, classes, parameters and detector MACs."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import Caller, State
from service.http.public_text import without_directories
from service.routes.errors_doc import error_responses
from service.schemas import ModelInfo, ModelsResponse

router = APIRouter(tags=["models"])


@router.get("/v1/models", response_model=ModelsResponse, responses=error_responses(401))
def list_models(state: State, caller: Caller) -> ModelsResponse:
    """Every served model, ready or not (with why not); ``default`` is the one used without ``?model=``. Checkpoints
    are named by their file (an admin key sees the paths as configured, directories included)."""
    infos = state.pool.describe()
    if not caller.admin:
        for info in infos:
            for key in ("detector_checkpoint", "segmenter_checkpoint", "error"):
                if info.get(key):
                    info[key] = without_directories(info[key]) or info[key]
    return ModelsResponse(default=state.pool.default, models=[ModelInfo(**info) for info in infos])
