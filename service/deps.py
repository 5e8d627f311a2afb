"""The app's shared state and the dependencies routes declare (``Annotated`` aliases)."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.accounting.billing import Billing
from service.accounting.ledger import Ledger
from service.accounting.metrics import ServiceMetrics
from service.accounting.tenants import Authenticator, Principal
from service.example_cache import ExampleCache
from service.http.errors import ApiError
from service.inference import ModelPool
from service.inputs.upload import UploadGate
from service.settings import Settings
from service.streams.history import StreamHistory
from service.streams.recording import StreamRecordings
from service.streams.store import StreamStore


@dataclass
class ServiceState:
    """Everything one app owns: settings, models, ledger and billing, metrics, authenticator, upload gate, and the
    streams' tracker state (in the ledger's database) and the earlier frames this replica ran."""

    settings: Settings
    pool: ModelPool
    ledger: Ledger
    billing: Billing
    metrics: ServiceMetrics
    auth: Authenticator
    uploads: UploadGate
    streams: StreamStore
    stream_history: StreamHistory
    examples: ExampleCache
    stream_recordings: StreamRecordings = field(default_factory=StreamRecordings)  # the frames this replica ran
    # bodies decoded off the event loop at once (V2 JSON tensors: the body, its text and its numbers in memory)
    request_decoding: asyncio.Semaphore = field(default_factory=lambda: asyncio.Semaphore(2))

    @property
    def ledger_error(self) -> str | None:
        """Why the usage ledger cannot be used now (None when it can): its state, kept live by the billing."""
        return self.billing.error


def get_state(request: Request) -> ServiceState:
    return request.app.state.service


_bearer = HTTPBearer(auto_error=False, description="API key as a bearer token")
_api_key = APIKeyHeader(name="X-API-Key", auto_error=False, description="API key")


def get_principal(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)],
    api_key: Annotated[str | None, Security(_api_key)],
) -> Principal:
    """The calling tenant: 401 for a missing or unknown key when keys are configured, 400 for ambiguous
    credentials (two keys, or a key beside another kind of ``Authorization``), whichever key would win."""
    api_keys = request.headers.getlist("x-api-key")
    authorizations = request.headers.getlist("authorization")
    if len(api_keys) > 1 or len(authorizations) > 1 or (api_keys and authorizations):
        raise ApiError(400, f"ambiguous credentials: {len(api_keys)} X-API-Key and {len(authorizations)} "
                            "Authorization headers; send exactly one of 'Authorization: Bearer KEY' or "
                            "'X-API-Key: KEY'", error="ambiguous_credentials")
    key = bearer.credentials if bearer is not None else api_key
    return get_state(request).auth.authenticate(key)


def get_admin(request: Request, caller: Annotated[Principal, Depends(get_principal)]) -> Principal:
    """A caller who may read every tenant's figures: 403 otherwise (anyone when no keys are configured)."""
    if get_state(request).auth.enabled and not caller.admin:
        raise ApiError(403, f"tenant {caller.tenant!r} may not read service-wide figures (an admin key is needed)")
    return caller


State = Annotated[ServiceState, Depends(get_state)]
Caller = Annotated[Principal, Depends(get_principal)]
Admin = Annotated[Principal, Depends(get_admin)]
