"""The app factory: ``create_app(settings)`` builds a FastAPI app that owns its model pool, usage
ledger and metrics registry. ``python -m service`` (``radarseg serve``) runs it behind the HTTP limits of the
settings (``service.server.http_server``), ``uvicorn --factory service.main:create_app`` plainly, and Ray Serve through
:func:`build_app`.

Models load and the ledger opens in the lifespan, so importing this module does no work; when a
checkpoint is missing or the database is unreachable the app still starts: ``/healthz`` answers 200,
``/readyz`` and ``/v1/segment`` answer 503 with the reason. At start-up, quota leases left expired by a
process that died are given back. ``python -m service`` runs the app with the HTTP limits of the
settings (head size, count and time, connections, port checked before the models load), answering while the
service imports and loading the models in the background (``create_app(..., load_in_background=True)``).
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from models.heap import freeze_loaded_heap
from service.accounting.billing import Billing
from service.accounting.ledger import Ledger
from service.accounting.metrics import MetricsMiddleware, ServiceMetrics
from service.accounting.tenants import Authenticator
from service.deps import ServiceState
from service.example_cache import ExampleCache
from service.http.errors import DeclaredBodyLimit, install_error_handlers
from service.http.security_headers import SecurityHeaders
from service.inference import ModelPool
from service.inputs.query import reject_unknown_query
from service.inputs.unread_body import CloseOnUnreadBody
from service.inputs.upload import UploadGate
from service.routes import examples, health, metrics, models, open_inference, segment, streams, usage, viewer
from service.routes.docs import install_docs
from service.schemas import ErrorBody
from service.settings import DEPLOYMENT_NAME, Settings  # noqa: F401 (DEPLOYMENT_NAME: deploy/serve.yaml's name)
from service.streams.history import StreamHistory
from service.streams.store import StreamStore

log = logging.getLogger(__name__)

DESCRIPTION = """ERASE-Net radar semantic segmentation. `POST /v1/segment` takes a `.npy` RAD cube and returns
objects, RA/RD masks and optionally the labelled RAD voxels, with per-request compute accounting (MACs per
stage, parameters, latency per stage, ROI voxels) and the tenant's usage. `POST /v1/streams` opens a stream whose
frames (`POST /v1/streams/{id}/frames?seq=N`) are segmented the same way and tracked across frames: each object's
track id and velocity vector, and the stream's tracks. Keys: `Authorization: Bearer KEY`
or `X-API-Key: KEY` when configured."""


def _open_ledger(state: ServiceState) -> None:
    """At start-up: open the ledger (a database that is down is noted, and the watch finds it back later)."""
    try:
        state.billing.open()
    except SQLAlchemyError as exc:
        state.billing.mark_down(exc)


def _load(state: ServiceState) -> None:
    """Open the ledger and load every model (blocking), logging each step."""
    log.info("opening the usage ledger (%s)", state.ledger.dialect)
    _open_ledger(state)
    state.pool.load()
    freeze_loaded_heap()  # a full garbage collection over torch and the models stalled a request every ~9 frames
    for name, model in state.pool.models.items():
        state.metrics.ready.labels(name).set(1 if model.ready else 0)
    log.info("ready: %s", "every model loaded" if state.pool.ready else f"not all loaded: {state.pool.errors()}")


def create_app(settings: Settings | None = None, *, load_in_background: bool = False) -> FastAPI:
    """Build the app (nothing loads until it starts: the lifespan loads models and opens the ledger). With
    ``load_in_background`` the lifespan returns at once and they load on a thread while the app answers
    (``/healthz`` 200, ``/readyz`` 503 ``loading`` with each model's stage, ``/v1/segment`` 503 not ready);
    otherwise start-up waits for them (the test client, Ray Serve replicas)."""
    settings = settings or Settings()
    os.environ.update(settings.models_environment())  # what models.* read from the environment, from the settings
    ledger = Ledger(settings.resolved_ledger_url(), table_prefix=settings.ledger_table_prefix,
                    timeout_s=settings.ledger_timeout_s)
    metrics_ = ServiceMetrics()
    stream_store = StreamStore(ledger, idle_s=settings.stream_idle_s, claim_s=settings.stream_claim_s,
                               max_per_tenant=settings.max_streams_per_tenant)  # its table beside the ledger's
    state = ServiceState(settings=settings, pool=ModelPool(settings), ledger=ledger,
                         billing=Billing(ledger, settings, metrics_), metrics=metrics_, auth=Authenticator(settings),
                         uploads=UploadGate(settings), streams=stream_store,
                         stream_history=StreamHistory(settings.stream_history_bytes),
                         examples=ExampleCache(settings.example_cache_bytes, examples.EXAMPLE_FRAMES))

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        loading = threading.Thread(target=_load, args=(state,), name="radarseg-load", daemon=True)
        if load_in_background:
            loading.start()
        else:
            await run_in_threadpool(_load, state)
        watch = asyncio.create_task(state.billing.watch(), name="radarseg-ledger-watch")
        try:
            yield
        finally:
            watch.cancel()
            if loading.is_alive():
                await run_in_threadpool(loading.join)
            state.pool.close()
            state.billing.close()
            state.ledger.dispose()

    app = FastAPI(title="radarseg", version="0.1.0", description=DESCRIPTION, lifespan=lifespan, docs_url=None,
                  redoc_url=None)
    app.state.service = state
    install_error_handlers(app)
    install_docs(app)
    # FastAPI's body limit on the one route that reads a body (GET routes never read one).
    # The API routes refuse query parameters they do not take (service.inputs.query); the viewer page reads its own.
    strict = [Depends(reject_unknown_query)]
    app.include_router(segment.router, max_body_size=settings.max_body_bytes, dependencies=strict)
    app.include_router(streams.router, max_body_size=settings.max_body_bytes, dependencies=strict)
    app.include_router(open_inference.router, max_body_size=settings.max_body_bytes, dependencies=strict)
    for router in (models.router, usage.router, examples.router):
        app.include_router(router, dependencies=strict)
    for router in (viewer.router, health.router, metrics.router):
        app.include_router(router)
    app.add_middleware(DeclaredBodyLimit, max_body_size=settings.max_body_bytes)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(CloseOnUnreadBody)
    app.add_middleware(MetricsMiddleware, metrics=state.metrics)  # added last: outermost, it sees every answer
    _document_errors_as_sent(app)
    return app


def _document_errors_as_sent(app: FastAPI) -> None:
    """The OpenAPI document as the service answers: parameter validation errors in the ErrorBody shape
    (service.http.errors) instead of FastAPI's default HTTPValidationError, and the 400 for ambiguous credentials
    on every operation that takes a key (service.deps.get_principal)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = build()
            ref = {"$ref": "#/components/schemas/ErrorBody"}
            spec["components"]["schemas"].setdefault("ErrorBody", ErrorBody.model_json_schema())
            for operations in spec["paths"].values():
                for operation in operations.values():
                    responses = operation.setdefault("responses", {})
                    if "422" in responses:
                        responses["422"]["content"] = {"application/json": {"schema": ref}}
                    if operation.get("security") and "400" not in responses:
                        responses["400"] = {"description": "Ambiguous credentials (two keys, or a key beside "
                                                           "another Authorization)",
                                            "content": {"application/json": {"schema": ref}}}
            for unused in ("HTTPValidationError", "ValidationError"):
                spec["components"]["schemas"].pop(unused, None)
            app.openapi_schema = spec
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def build_app(args: dict[str, Any]) -> Any:
    """Ray Serve's application builder (``import_path: service.main:build_app`` in deploy/serve.yaml): the app of
    :func:`create_app` in each replica, with ``args["settings"]`` overriding the ``RADARSEG_*`` environment (Ray is
    imported only here)."""
    from service.ray_serve import build_app as build

    return build(args, create_app)
