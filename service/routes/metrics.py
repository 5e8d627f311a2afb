"""GET /metrics: the app's Prometheus registry in the text exposition format."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from service.deps import State

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}})
def metrics(state: State) -> Response:
    """Request and stage latency histograms (s), MACs and request counters per model and tenant, errors by code."""
    for name, model in state.pool.models.items():
        state.metrics.ready.labels(name).set(1 if model.ready else 0)
        state.metrics.queue.labels(name).set(model.held)
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
