"""GET /metrics: the app's Prometheus registry in the text exposition format."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.deps import Admin, State
from service.routes.errors_doc import error_responses

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}},
                             "description": "Prometheus text format"}, **error_responses(400, 401, 403)})
def metrics(state: State, admin: Admin) -> Response:
    """Request and stage latency histograms (s), MACs and request counters per model and tenant, errors by code.
    With API keys configured, only an admin key may read them (the series name every tenant)."""
    for name, model in state.pool.models.items():
        state.metrics.ready.labels(name).set(1 if model.ready else 0)
        state.metrics.queue.labels(name).set(model.held)
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
