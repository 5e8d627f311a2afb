"""Quota billing of segmentation requests: a lease on the tenant's daily MAC quota before inference, the
request billed after it (``service.ledger`` holds the counters and the two atomic steps).

The reservation estimate is the tenant's own: the largest MACs billed to it for the model among its last
``HISTORY`` requests (in the ledger, so it survives restarts and is shared by every process on the same ledger);
a tenant with no history yet reserves the detector's exact MACs plus ``reservation_headroom`` times the largest
segmenter MACs of the model's warm-up scenes (the same for every tenant). Another tenant's cubes never raise it,
and neither does a request refused at settlement (only billed requests are history). A request whose actual cost
exceeds what is left is refused at settlement (429) and not billed;
``radarseg_rejected_requests{reason="quota_at_settlement"}`` counts those, the inference wasted.

A 429 at reservation says when to retry: when the tenant's billed MACs leave room for the request but its own
requests in flight hold the rest, ``Retry-After`` is the deadline of the lease that frees enough (they usually end
much sooner); when the billed MACs alone leave too little, the next UTC day.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any, TypeVar

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from models.erasenet.compute_report import FrameCompute
from service.errors import ApiError
from service.inference import ServedModel
from service.ledger import DayTotals, Lease, Ledger, QuotaExceeded
from service.metrics import ServiceMetrics
from service.schemas import RequestUsage
from service.settings import Settings

log = logging.getLogger(__name__)
T = TypeVar("T")
HISTORY = 50  # a tenant's last billed requests of a model that its reservation estimate reads


def seconds_to_utc_midnight(now: dt.datetime | None = None) -> int:
    """Seconds until the next UTC day (when a daily quota starts afresh), at least 1."""
    now = now or dt.datetime.now(dt.UTC)
    tomorrow = dt.datetime.combine(now.date() + dt.timedelta(days=1), dt.time(), tzinfo=dt.UTC)
    return max(1, int((tomorrow - now).total_seconds()) + 1)


def quota_error(exc: QuotaExceeded, now: dt.datetime | None = None) -> ApiError:
    """429 saying what was used, held and asked for, with Retry-After until enough of the quota frees: the
    deadline of the tenant's own leases when they are what holds it, else the next UTC day."""
    now = now or dt.datetime.now(dt.UTC)
    if exc.frees_at is not None:
        retry_after = max(1, int((exc.frees_at - now).total_seconds()) + 1)
        why = (f"{exc.reserved_macs} MACs are held by the tenant's requests in flight; enough is free once they end "
               f"(at the latest in {retry_after} s, their lease deadline)")
    else:
        retry_after = seconds_to_utc_midnight(now)
        why = f"the quota is spent until the next UTC day ({exc.reserved_macs} MACs held by requests in flight)"
    return ApiError(
        429, f"daily MAC quota of tenant {exc.tenant!r} does not cover the request: {exc.used_macs} of "
             f"{exc.limit_macs} MACs used on {exc.day.isoformat()}, this request needs about {exc.requested_macs}; "
             f"{why}",
        headers={"Retry-After": str(retry_after)}, tenant=exc.tenant, day=exc.day.isoformat(),
        used_macs=exc.used_macs, limit_macs=exc.limit_macs, reserved_macs=exc.reserved_macs,
        requested_macs=exc.requested_macs)


class QuotaHold:
    """One request's hold on its tenant's quota, from :meth:`Billing.hold`: the lease taken on entering, billed by
    :meth:`settle` or given back when the block is left any other way."""

    def __init__(self, billing: Billing, tenant: str, lease: Lease | None) -> None:
        self.billing = billing
        self.tenant = tenant
        self.lease = lease
        self.ended = False

    async def settle(self, *, model: str, compute: FrameCompute, request_id: str) -> RequestUsage:
        """Bill the request (see :meth:`Billing.settle`); the lease ends with it, billed or refused."""
        self.ended = True
        return await self.billing.settle(self.tenant, self.lease, model=model, compute=compute, request_id=request_id)


class Billing:
    """Reserve, settle and release one tenant's quota for one request; every ledger call runs on a worker
    thread and a database failure is a 503 (never a 500, never a request billed twice)."""

    def __init__(self, ledger: Ledger, settings: Settings, metrics: ServiceMetrics) -> None:
        self.ledger = ledger
        self.settings = settings
        self.metrics = metrics

    async def _call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        try:
            return await run_in_threadpool(fn, *args, **kwargs)
        except SQLAlchemyError as exc:
            raise ApiError(503, f"usage ledger unavailable ({type(exc).__name__}); the request was not billed",
                           error="ledger_unavailable",
                           headers={"Retry-After": str(self.settings.retry_after_s)}) from None

    def start(self) -> int:
        """At start-up (blocking): give back expired leases of processes that died; the MACs given back."""
        reclaimed = self.ledger.reclaim_expired()
        if reclaimed:
            log.warning("reclaimed %d MACs of expired quota leases (requests cut off by a crash)", reclaimed)
        return reclaimed

    def estimate(self, served: ServedModel, tenant: str) -> int:
        """MACs to reserve before running (blocking: reads the ledger): the largest of ``tenant``'s own recent
        billed requests of the model, else the detector's exact MACs plus headroom times the warm-up's segmenter
        MACs."""
        own = self.ledger.recent_max_macs(served.spec.name, tenant=tenant, last=HISTORY)
        if own > 0:
            return own
        return served.net.detector_macs() + int(self.settings.reservation_headroom * served.segment_macs_high)

    def _reserve(self, tenant: str, served: ServedModel, quota: int) -> Lease | QuotaExceeded:
        return self.ledger.reserve(tenant, self.estimate(served, tenant), quota, lease_s=self.settings.lease_s)

    async def check(self, tenant: str, served: ServedModel) -> None:
        """ApiError 429 when ``tenant``'s quota cannot cover a request of ``served`` now (before its body is
        read; :meth:`reserve` decides after it)."""
        quota = self.settings.quota_for(tenant)
        if quota is None:
            return
        refused = await self._call(lambda: self.ledger.check(tenant, self.estimate(served, tenant), quota))
        if refused is not None:
            self.metrics.rejected.labels(served.spec.name, "quota").inc()
            raise quota_error(refused)

    async def reserve(self, tenant: str, served: ServedModel) -> Lease | None:
        """A lease on ``tenant``'s quota for one request of ``served`` (None: the tenant has no quota);
        ApiError 429 when it does not fit."""
        quota = self.settings.quota_for(tenant)
        if quota is None:
            return None
        outcome = await self._call(self._reserve, tenant, served, quota)
        if isinstance(outcome, QuotaExceeded):
            self.metrics.rejected.labels(served.spec.name, "quota").inc()
            raise quota_error(outcome)
        return outcome

    @asynccontextmanager
    async def hold(self, tenant: str, served: ServedModel, *,
                   on_refused: Callable[[], None] | None = None) -> AsyncIterator[QuotaHold]:
        """``async with billing.hold(tenant, served) as quota``: reserve on entering (ApiError 429 when it does not
        fit), ``await quota.settle(...)`` inside; leaving without settling (an error, a cancelled request) gives
        the reservation back."""
        try:
            lease = await self.reserve(tenant, served)
        except BaseException:
            if on_refused is not None:  # e.g. give back the model slot taken before the quota was touched
                on_refused()
            raise
        held = QuotaHold(self, tenant, lease)
        try:
            yield held
        finally:
            if not held.ended:
                await self.release(held.lease)

    async def release(self, lease: Lease | None) -> None:
        """Give a lease back (the request was not billed)."""
        if lease is not None:
            await self._call(self.ledger.release, lease)

    async def settle(self, tenant: str, lease: Lease | None, *, model: str, compute: FrameCompute,
                     request_id: str) -> RequestUsage:
        """Bill the request (its MACs and compute time, ``compute.compute_us``) and end its lease; the tenant's
        day after it. ApiError 429 (nothing billed) when its actual MACs no longer fit the quota."""
        quota = self.settings.quota_for(tenant)
        billed = await self._call(
            self.ledger.settle, tenant, model=model, macs=compute.macs_total, compute_us=compute.compute_us,
            roi_voxels=compute.roi_voxels, lease=lease, limit=quota, request_id=request_id)
        if isinstance(billed, QuotaExceeded):
            self.metrics.rejected.labels(model, "quota_at_settlement").inc()
            raise quota_error(billed)
        return request_usage(billed, quota)


def request_usage(totals: DayTotals, quota: int | None) -> RequestUsage:
    return RequestUsage(tenant=totals.tenant, day=totals.day.isoformat(), requests=totals.requests, macs=totals.macs,
                        compute_seconds=totals.compute_seconds, quota_macs=quota,
                        remaining_macs=None if quota is None else max(0, quota - totals.macs))
