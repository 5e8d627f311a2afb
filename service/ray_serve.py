"""Ray Serve deployment of the HTTP service: the very app of ``service.main.create_app`` behind
``@serve.ingress``, for scale-out across a Ray cluster (docs/design.md section 13).

::

    serve run deploy/serve.yaml                                     # a local Ray, or RAY_ADDRESS's cluster
    serve deploy deploy/serve.yaml --address http://127.0.0.1:8265  # onto a running cluster

(``import_path: service.main:build_app``, beside the app factory, imports this module when Serve calls it.)

Each replica is a Ray actor that builds its own app in the replica (``__serve_build_asgi_app__``, called
once after ``__init__``), so its lifespan loads the models once per replica and opens the usage ledger;
the routes, errors, metrics, keys and quotas are exactly those of the uvicorn service. Settings come
from the replica's environment (``RADARSEG_*``, set through ``runtime_env.env_vars`` in the Serve config)
and from the ``settings`` argument of the application builder (``args: {settings: {...}}`` in the
config), which override the environment. Replicas share one usage ledger only through a database they
all reach: set ``RADARSEG_LEDGER_URL`` to PostgreSQL when replicas run on several nodes.

Serve's own queueing (``max_ongoing_requests`` per replica) sits in front of the app's model pool
(``RADARSEG_REPLICAS`` model instances and ``RADARSEG_MAX_QUEUE`` waiting requests per replica, 503
beyond): keep ``max_ongoing_requests <= RADARSEG_REPLICAS + RADARSEG_MAX_QUEUE`` so that the router,
not the app, holds the overflow.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from ray import serve
from ray.serve import Application

from service.settings import DEPLOYMENT_NAME, Settings

AppFactory = Callable[[Settings], FastAPI]


@serve.deployment(name=DEPLOYMENT_NAME, max_ongoing_requests=2, ray_actor_options={"num_cpus": 1})
@serve.ingress()
class RadarsegService:
    """One replica: settings from its environment plus ``settings`` overrides; the app is built in the replica by
    ``factory`` (``service.main.create_app``, handed over by its caller: this module never imports the app's)."""

    def __init__(self, settings: dict[str, Any] | None = None, factory: AppFactory | None = None) -> None:
        self.settings = Settings(**(settings or {}))  # refused here (replica start fails) when invalid
        if factory is None:
            raise ValueError("RadarsegService needs the app factory: bind(settings, service.main.create_app)")
        self.factory = factory

    def __serve_build_asgi_app__(self) -> FastAPI:
        """Serve calls this once per replica, after ``__init__``; the app's lifespan then loads the models."""
        return self.factory(self.settings)


def build_app(args: dict[str, Any], factory: AppFactory) -> Application:
    """Application builder (``service.main.build_app``; ``args`` from the Serve config): ``settings`` is a mapping
    of Settings fields that override the ``RADARSEG_*`` environment; ``factory`` builds each replica's app."""
    unknown = set(args) - {"settings"}
    if unknown:
        raise ValueError(f"unknown application arguments {sorted(unknown)}; expected only 'settings'")
    settings = args.get("settings") or {}
    if not isinstance(settings, dict):
        raise ValueError(f"'settings' must be a mapping of service settings, got {type(settings).__name__}")
    return RadarsegService.bind(settings, factory)

