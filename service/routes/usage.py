"""GET /v1/usage: the caller's tenant usage (every tenant's, or a chosen one, for an admin key)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from service.accounting.ledger import DayTotals, utc_today
from service.deps import Caller, State
from service.http.errors import ApiError
from service.routes.errors_doc import error_responses
from service.schemas import DayUsage, HeldQuota, TenantUsage, UsageResponse, UsageTotals

router = APIRouter(tags=["usage"])


def _day(totals: DayTotals) -> DayUsage:
    return DayUsage(day=totals.day.isoformat(), requests=totals.requests, macs=totals.macs,
                    compute_seconds=totals.compute_seconds)


@router.get("/v1/usage", response_model=UsageResponse, responses=error_responses(400, 401, 403, 422, 503))
async def usage(
    state: State,
    caller: Caller,
    tenant: Annotated[str | None, Query(description="admin keys only: one tenant; 'all' for every tenant",
                                       max_length=64)] = None,
    days: Annotated[int, Query(ge=1, le=366, description="days listed per tenant, newest first")] = 31,
) -> UsageResponse:
    """Requests, MACs and compute seconds per UTC day and in total, with the daily MAC quota and today's
    quota reservations held by requests in flight (or left by requests a crash cut off, until they expire)."""
    if tenant is None or tenant == caller.tenant:
        tenants: list[str] | None = [caller.tenant]
    elif not caller.admin:
        raise ApiError(403, f"tenant {caller.tenant!r} may read its own usage only (other tenants need an admin key)")
    else:
        tenants = None if tenant == "all" else [tenant]
    # on the ledger's own threads, each call bounded: a database that is down or silent is a 503, never a 500
    read = state.billing.read
    by_tenant = await read(state.ledger.days, tenants, limit_days=days)
    all_time = await read(state.ledger.all_time, tenants)
    names = sorted(set(by_tenant) | set(tenants or state.settings.tenants))
    today = utc_today()
    held = await read(lambda: {name: state.ledger.held(name, today) for name in names})
    out = []
    for name in names:
        listed = by_tenant.get(name, [])
        today_totals = next((d for d in listed if d.day == today), DayTotals(name, today, 0, 0, 0))
        total = all_time.get(name, DayTotals(name, today, 0, 0, 0))
        out.append(TenantUsage(
            tenant=name, quota_macs=state.settings.quota_for(name), today=_day(today_totals),
            held=HeldQuota(**vars(held[name]), lease_seconds=state.settings.lease_s),
            total=UsageTotals(requests=total.requests, macs=total.macs, compute_seconds=total.compute_seconds),
            days=[_day(d) for d in listed]))
    return UsageResponse(tenants=out)
