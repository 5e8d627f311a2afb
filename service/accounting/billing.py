"""Quota billing of segmentation requests: a lease on the tenant's daily MAC quota before inference, the
request billed after it (``service.accounting.ledger`` holds the counters and the two atomic steps).

The reservation estimate is the tenant's own: the largest MACs billed to it for the model among its last
``HISTORY`` requests (in the ledger, so it survives restarts and is shared by every process on the same ledger);
a tenant with no history yet reserves the detector's exact MACs plus ``reservation_headroom`` times the largest
segmenter MACs of the model's warm-up scenes (the same for every tenant). Another tenant's cubes never raise it,
and neither does a request refused at reservation (only billed requests are history). Compute is always billed: a
request that ran is billed for what it ran, even past the quota (a reservation admits a request only while the
quota covers its estimate, so a tenant runs at most one frame's compute beyond its quota; its next request is
refused).

The ledger's database: every call runs on threads of the billing's own (``ledger_threads``, never the threads the
plain routes and ``/healthz`` use) and waits at most ``ledger_timeout_s``; a database error or a silent database is
a 503. The first failure marks the ledger down: requests that need it answer 503 at once, ``/readyz`` says why,
and :meth:`Billing.watch` probes it every ``ledger_check_s`` (opening it if the service started without it), gives
back the leases that failures left behind, and marks it up again.

A 429 at reservation says when to retry: when the tenant's billed MACs leave room for the request but its own
requests in flight hold the rest, ``Retry-After`` is the deadline of the lease that frees enough (they usually end
much sooner); when the billed MACs alone leave too little, the next UTC day.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import functools
import logging
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from typing import Any, TypeVar

from sqlalchemy.exc import SQLAlchemyError

from models.erasenet.compute_report import FrameCompute
from service.accounting.ledger import DayTotals, Lease, Ledger, QuotaExceeded
from service.accounting.metrics import ServiceMetrics
from service.http.errors import ApiError
from service.inference import ServedModel
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
        """Bill the request (see :meth:`Billing.settle`); the lease ends with it. When the ledger fails here the
        request is not billed (503) and its lease is given back once the ledger answers again."""
        self.ended = True
        try:
            return await self.billing.settle(self.tenant, self.lease, model=model, compute=compute,
                                             request_id=request_id)
        except ApiError:
            if self.lease is not None:
                self.billing.left_behind.append(self.lease)
            raise


class Billing:
    """Reserve, settle and release one tenant's quota for one request; every ledger call runs on a worker
    thread and a database failure is a 503 (never a 500, never a request billed twice)."""

    def __init__(self, ledger: Ledger, settings: Settings, metrics: ServiceMetrics) -> None:
        self.ledger = ledger
        self.settings = settings
        self.metrics = metrics
        self.error: str | None = None  # why the ledger cannot be used now (None: it can, or was not tried yet)
        self.opened = False
        self.left_behind: list[Lease] = []  # leases whose release failed: given back once the database answers
        self._threads = ThreadPoolExecutor(settings.ledger_threads, thread_name_prefix="ledger")
        self._probe = ThreadPoolExecutor(1, thread_name_prefix="ledger-probe")  # never queued behind requests

    def unavailable(self, why: str) -> ApiError:
        return ApiError(503, f"usage ledger unavailable ({why}); the request was not billed",
                        error="ledger_unavailable", headers={"Retry-After": str(self.settings.retry_after_s)})

    def mark_down(self, exc: BaseException) -> None:
        why = ("no answer within the ledger timeout" if isinstance(exc, TimeoutError)
               else f"{type(exc).__name__}: {(str(exc).splitlines() or [''])[0]}")
        if self.error is None or not self.opened:
            log.error("usage ledger %s unavailable: %s", self.ledger.dialect, why)
        self.error = why

    async def _call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """``fn`` on a ledger thread, waiting at most ``ledger_timeout_s``; a 503 while the ledger is down, on a
        database error and on a silent database (which marks it down)."""
        if self.error is not None:
            raise self.unavailable(self.error)
        return await self.run(self._threads, fn, *args, **kwargs)

    async def run(self, threads: ThreadPoolExecutor, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        future = asyncio.get_running_loop().run_in_executor(threads, functools.partial(fn, *args, **kwargs))
        try:
            return await asyncio.wait_for(future, self.settings.ledger_timeout_s)
        except (SQLAlchemyError, TimeoutError) as exc:
            self.mark_down(exc)
            raise self.unavailable(self.error or "") from None

    async def read(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """A ledger read for a route (``GET /v1/usage``), under the same rules as billing's own calls."""
        return await self._call(fn, *args, **kwargs)

    def open(self) -> None:
        """Create the tables if needed, check the database answers and give back expired leases (blocking)."""
        self.ledger.create()
        self.ledger.ping()
        self.start()
        self.opened, self.error = True, None

    def _recover(self) -> int:
        """The probe's work (blocking): open or ping the ledger, then give back the leases failures left."""
        if self.opened:
            self.ledger.ping()
        else:
            self.open()
        given = 0
        while self.left_behind:
            lease = self.left_behind[0]
            self.ledger.release(lease)
            self.left_behind.pop(0)
            given += lease.macs
        return given

    async def watch(self) -> None:
        """Keep the ledger's state live (the app's lifespan runs this): every ``ledger_check_s`` a probe on a thread
        of its own; the ledger is marked down when it fails or is silent, and up (with the leases left behind
        given back) when it answers again."""
        while True:
            await asyncio.sleep(self.settings.ledger_check_s)
            was = self.error
            try:
                given = await self.run(self._probe, self._recover)
            except ApiError:
                continue
            if given:
                log.warning("gave back %d MACs of quota leases held when the ledger failed", given)
            if was is not None:
                log.warning("usage ledger %s available again", self.ledger.dialect)
            self.error = None

    def close(self) -> None:
        self._threads.shutdown(wait=False, cancel_futures=True)
        self._probe.shutdown(wait=False, cancel_futures=True)

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
        """Give a lease back (the request was not billed). When the ledger fails, the lease is kept and given back
        once it answers again (:meth:`watch`), so no tenant stays locked out for a lease's whole life."""
        if lease is None:
            return
        try:
            await self._call(self.ledger.release, lease)
        except ApiError:
            self.left_behind.append(lease)

    async def settle(self, tenant: str, lease: Lease | None, *, model: str, compute: FrameCompute,
                     request_id: str) -> RequestUsage:
        """Bill the request (its MACs and compute time, ``compute.compute_us``) and end its lease; the tenant's
        day after it. What ran is billed, even past the quota (the reservation admitted it while the quota covered
        its estimate)."""
        quota = self.settings.quota_for(tenant)
        billed = await self._call(
            self.ledger.settle, tenant, model=model, macs=compute.macs_total, compute_us=compute.compute_us,
            roi_voxels=compute.roi_voxels, lease=lease, limit=None, request_id=request_id)
        return request_usage(billed, quota)


def request_usage(totals: DayTotals, quota: int | None) -> RequestUsage:
    return RequestUsage(tenant=totals.tenant, day=totals.day.isoformat(), requests=totals.requests, macs=totals.macs,
                        compute_seconds=totals.compute_seconds, quota_macs=quota,
                        remaining_macs=None if quota is None else max(0, quota - totals.macs))
