"""The app's shared state and the dependencies routes declare (``Annotated`` aliases)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.inference import ModelPool
from service.ledger import Ledger
from service.metrics import ServiceMetrics
from service.settings import Settings
from service.tenants import Authenticator, Principal


@dataclass
class ServiceState:
    """Everything one app owns: settings, models, ledger, metrics, authenticator."""

    settings: Settings
    pool: ModelPool
    ledger: Ledger
    metrics: ServiceMetrics
    auth: Authenticator
    ledger_error: str | None = field(default="not opened yet")


def get_state(request: Request) -> ServiceState:
    return request.app.state.service


_bearer = HTTPBearer(auto_error=False, description="API key as a bearer token")
_api_key = APIKeyHeader(name="X-API-Key", auto_error=False, description="API key")


def get_principal(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)],
    api_key: Annotated[str | None, Security(_api_key)],
) -> Principal:
    """The calling tenant (401 for a missing or unknown key when keys are configured)."""
    key = bearer.credentials if bearer is not None else api_key
    return get_state(request).auth.authenticate(key)


State = Annotated[ServiceState, Depends(get_state)]
Caller = Annotated[Principal, Depends(get_principal)]
