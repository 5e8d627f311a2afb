"""GET /healthz (the process answers) and GET /readyz (models loaded and ledger reachable)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.deps import State
from service.http.public_text import without_directories
from service.schemas import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Liveness: 200 whenever the process serves HTTP, ready or not."""
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness, "description": "Not ready"}})
def readyz(state: State) -> JSONResponse:
    """Readiness: 200 when every model is loaded and the ledger is reachable, else 503 with the reasons (``status``
    ``loading`` while the models load, with each one's stage in ``progress``)."""
    ready = state.pool.ready and state.ledger_error is None
    status = "ready" if ready else "loading" if state.pool.loading else "not_ready"
    body = Readiness(ready=ready, status=status, progress=state.pool.progress(),
                     models={name: None if why is None else without_directories(why)
                             for name, why in state.pool.errors().items()},
                     ledger=state.ledger_error)
    headers = {} if body.ready else {"Retry-After": str(state.settings.retry_after_s)}
    return JSONResponse(body.model_dump(), status_code=200 if body.ready else 503, headers=headers)


