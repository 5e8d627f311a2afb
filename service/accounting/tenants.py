"""Tenants by API key: ``Authorization: Bearer KEY`` or ``X-API-Key: KEY``.

With no keys configured every request belongs to one anonymous tenant. Keys are compared in constant
time against their SHA-256 digests; the plain keys are not kept after start-up.
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass

from service.http.errors import ApiError
from service.settings import ANONYMOUS_TENANT, Settings


@dataclass(frozen=True)
class Principal:
    """Who is calling: the tenant billed, and whether it may read every tenant's usage."""

    tenant: str
    admin: bool = False


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode("utf-8")).digest()


class Authenticator:
    """Maps a presented key to its tenant."""

    def __init__(self, settings: Settings) -> None:
        self._keys = [(_digest(key), tenant) for key, tenant in settings.tenant_for_key().items()]
        self._admins = frozenset(settings.admin_tenants)

    @property
    def enabled(self) -> bool:
        return bool(self._keys)

    def authenticate(self, key: str | None) -> Principal:
        """The caller's principal; ApiError 401 for a missing or unknown key when keys are configured."""
        if not self._keys:
            return Principal(ANONYMOUS_TENANT)
        if not key:
            raise ApiError(401, "missing API key: send 'Authorization: Bearer KEY' or 'X-API-Key: KEY'",
                           headers={"WWW-Authenticate": "Bearer"})
        digest = _digest(key)
        tenant = None
        for known, owner in self._keys:  # no early exit: the time taken does not depend on which key matched
            if hmac.compare_digest(known, digest):
                tenant = owner
        if tenant is None:
            raise ApiError(401, "unknown API key", headers={"WWW-Authenticate": "Bearer"})
        return Principal(tenant, admin=tenant in self._admins)
