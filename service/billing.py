"""Quota billing of segmentation requests: a lease on the tenant's daily MAC quota before inference, the
request billed after it (``service.ledger`` holds the counters and the two atomic steps).

The reservation estimate is conservative from the first request on: the detector's exact MACs plus
``reservation_headroom`` times the largest segmenter MACs known for the model, from its warm-up scenes,
the requests this process served and the ledger's recent billed requests (which survive restarts and are
shared by every process on the same ledger). A request whose actual cost still exceeds what is left is
refused at settlement (429) and not billed; ``radarseg_rejected_requests{reason="quota_at_settlement"}``
counts those, the inference wasted.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from models.compute_report import FrameCompute
from service.errors import ApiError
from service.inference import ServedModel
from service.ledger import DayTotals, Lease, Ledger, QuotaExceeded
from service.metrics import ServiceMetrics
from service.schemas import RequestUsage
from service.settings import Settings

log = logging.getLogger(__name__)
T = TypeVar("T")


def seconds_to_utc_midnight(now: dt.datetime | None = None) -> int:
    """Seconds until the next UTC day (when a daily quota starts afresh), at least 1."""
    now = now or dt.datetime.now(dt.UTC)
    tomorrow = dt.datetime.combine(now.date() + dt.timedelta(days=1), dt.time(), tzinfo=dt.UTC)
    return max(1, int((tomorrow - now).total_seconds()) + 1)


def quota_error(exc: QuotaExceeded) -> ApiError:
    """429 saying what was used, held and asked for, with Retry-After until the quota renews."""
    return ApiError(
        429, f"daily MAC quota of tenant {exc.tenant!r} exhausted: {exc.used_macs} of {exc.limit_macs} MACs used on "
             f"{exc.day.isoformat()} ({exc.reserved_macs} held by requests in flight), this request needs about "
             f"{exc.requested_macs}",
        headers={"Retry-After": str(seconds_to_utc_midnight())}, tenant=exc.tenant, day=exc.day.isoformat(),
        used_macs=exc.used_macs, limit_macs=exc.limit_macs, reserved_macs=exc.reserved_macs,
        requested_macs=exc.requested_macs)


class Billing:
    """Reserve, settle and release one tenant's quota for one request; every ledger call runs on a worker
    thread and a database failure is a 503 (never a 500, never a request billed twice)."""

    def __init__(self, ledger: Ledger, settings: Settings, metrics: ServiceMetrics) -> None:
        self.ledger = ledger
        self.settings = settings
        self.metrics = metrics
        self._ledger_max: dict[str, int] = {}  # model -> largest billed MACs among its recent requests

    async def _call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        try:
            return await run_in_threadpool(fn, *args, **kwargs)
        except SQLAlchemyError as exc:
            raise ApiError(503, f"usage ledger unavailable ({type(exc).__name__}); the request was not billed",
                           error="ledger_unavailable",
                           headers={"Retry-After": str(self.settings.retry_after_s)}) from None

    def start(self, models: list[str]) -> int:
        """At start-up (blocking): give back expired leases of processes that died, and read each model's
        recent maximum from the ledger; the MACs given back."""
        reclaimed = self.ledger.reclaim_expired()
        if reclaimed:
            log.warning("reclaimed %d MACs of expired quota leases (requests cut off by a crash)", reclaimed)
        for model in models:
            self._ledger_max[model] = self.ledger.recent_max_macs(model)
        return reclaimed

    def estimate(self, served: ServedModel) -> int:
        """MACs to reserve before running: exact for the detector, a bound with headroom for the segmenter."""
        detector = served.net.detector_macs()
        known = max(served.segment_macs_high, self._ledger_max.get(served.spec.name, 0) - detector, 0)
        return detector + int(self.settings.reservation_headroom * known)

    async def reserve(self, tenant: str, served: ServedModel) -> Lease | None:
        """A lease on ``tenant``'s quota for one request of ``served`` (None: the tenant has no quota);
        ApiError 429 when it does not fit."""
        quota = self.settings.quota_for(tenant)
        if quota is None:
            return None
        outcome = await self._call(self.ledger.reserve, tenant, self.estimate(served), quota,
                                   lease_s=self.settings.lease_s)
        if isinstance(outcome, QuotaExceeded):
            self.metrics.rejected.labels(served.spec.name, "quota").inc()
            raise quota_error(outcome)
        return outcome

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
        self._ledger_max[model] = max(self._ledger_max.get(model, 0), compute.macs_total)
        return request_usage(billed, quota)


def request_usage(totals: DayTotals, quota: int | None) -> RequestUsage:
    return RequestUsage(tenant=totals.tenant, day=totals.day.isoformat(), requests=totals.requests, macs=totals.macs,
                        compute_seconds=totals.compute_seconds, quota_macs=quota,
                        remaining_macs=None if quota is None else max(0, quota - totals.macs))
