"""GET /v1/models: the served models, their presets, classes, parameters and detector MACs."""

from __future__ import annotations

from fastapi import APIRouter

from service.deps import Caller, State
from service.routes.errors_doc import error_responses
from service.schemas import ModelInfo, ModelsResponse

router = APIRouter(tags=["models"])


@router.get("/v1/models", response_model=ModelsResponse, responses=error_responses(401))
def list_models(state: State, caller: Caller) -> ModelsResponse:
    """Every served model, ready or not (with why not); ``default`` is the one used without ``?model=``."""
    return ModelsResponse(default=state.pool.default, models=[ModelInfo(**info) for info in state.pool.describe()])
