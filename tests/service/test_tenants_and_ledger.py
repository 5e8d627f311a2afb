"""Keys and tenant isolation, the daily quota under concurrency, ledger exactness under concurrent
requests and across a restart (SQLite through the app; SQLite and PostgreSQL through the Ledger)."""

from __future__ import annotations

import datetime as dt
from concurrent.futures import ThreadPoolExecutor

import pytest
from pydantic import ValidationError

from service.accounting.ledger import Ledger, QuotaExceeded
from service.settings import Settings
from tests.service.conftest import KEYS, NPY

ACME, GLOBEX, ADMIN = (f"Bearer {key}" for key in KEYS)


def _auth(value: str) -> dict[str, str]:
    return {**NPY, "authorization": value}


def test_keys_tenants_and_admin(make_settings, client_for, cube_body):
    client = client_for(make_settings(api_keys=KEYS, admin_tenants=["ops"]))
    assert client.post("/v1/segment", content=cube_body, headers=NPY).status_code == 401
    r = client.post("/v1/segment", content=cube_body, headers=_auth("Bearer key-nobody-0123456789abcdef"))
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert client.get("/v1/models").status_code == 401
    acme = client.post("/v1/segment", content=cube_body, headers=_auth(ACME))
    assert acme.status_code == 200 and acme.json()["usage"]["tenant"] == "acme"
    # X-API-Key works too
    x_key = client.post("/v1/segment", content=cube_body, headers={**NPY, "x-api-key": next(iter(KEYS))})
    assert x_key.json()["usage"]["requests"] == 2

    mine = client.get("/v1/usage", headers={"authorization": ACME}).json()["tenants"]
    assert [t["tenant"] for t in mine] == ["acme"] and mine[0]["today"]["requests"] == 2
    theirs = client.get("/v1/usage", headers={"authorization": GLOBEX}).json()["tenants"]
    assert [t["tenant"] for t in theirs] == ["globex"] and theirs[0]["total"]["requests"] == 0
    assert client.get("/v1/usage?tenant=acme", headers={"authorization": GLOBEX}).status_code == 403
    assert client.get("/v1/usage?tenant=all", headers={"authorization": GLOBEX}).status_code == 403
    every = client.get("/v1/usage?tenant=all", headers={"authorization": ADMIN}).json()["tenants"]
    assert {t["tenant"]: t["total"]["requests"] for t in every} == {"acme": 2, "globex": 0, "ops": 0}
    one = client.get("/v1/usage?tenant=acme", headers={"authorization": ADMIN}).json()["tenants"]
    assert one[0]["total"]["macs"] == acme.json()["compute"]["macs"]["total"] + x_key.json()["compute"]["macs"]["total"]


@pytest.mark.parametrize(("overrides", "message"), [
    ({"api_keys": {"short": "acme"}}, "at least 16 characters"),
    ({"api_keys": {"key-acme-0123456789abcdef": "Acme Corp"}}, "tenant name"),
    ({"host": "0.0.0.0"}, "without API keys"),
    ({"admin_tenants": ["ops"]}, "have no API key"),
    ({"ledger_url": "mysql://x/y"}, "sqlite:// or postgresql"),
    ({"max_body_bytes": 1 << 40}, "less than or equal"),
    ({"max_queue": -1}, "greater than or equal"),
    ({"ledger_table_prefix": "x; drop table"}, "must match"),
    ({"default_model": "other"}, "not one of the models"),
])
def test_unsafe_settings_are_refused(overrides, message):
    with pytest.raises(ValidationError, match=message):
        Settings(**overrides)


def test_quota_holds_under_concurrent_requests(make_settings, client_for, cube_body):
    client = client_for(make_settings(api_keys=KEYS, tenant_quotas={"acme": 0}, daily_mac_quota=None))
    first = client.post("/v1/segment", content=cube_body, headers=_auth(GLOBEX))  # unlimited: learn the cost
    per_request = first.json()["compute"]["macs"]["total"]
    refused = client.post("/v1/segment", content=cube_body, headers=_auth(ACME))
    assert refused.status_code == 429 and refused.json()["limit_macs"] == 0 and int(refused.headers["retry-after"]) > 0

    client = client_for(make_settings(api_keys=KEYS, tenant_quotas={"acme": 3 * per_request + per_request // 2},
                                      data_dir=client.app.state.service.settings.data_dir.parent / "quota"))
    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(lambda _: client.post("/v1/segment", content=cube_body, headers=_auth(ACME)),
                                range(8)))
    billed = sum(r.status_code == 200 for r in answers)
    # Reservations are conservative (headroom over the largest cost known), so a burst may be admitted a little
    # below the quota, but every admitted request is billed: none is refused after running.
    assert 2 <= billed <= 3 and all(r.status_code in (200, 429) for r in answers), [r.status_code for r in answers]
    for r in answers:
        if r.status_code == 429:
            body = r.json()
            assert body["tenant"] == "acme" and body["limit_macs"] == 3 * per_request + per_request // 2
            assert body["used_macs"] <= body["limit_macs"] and body["requested_macs"] >= per_request
    state = client.app.state.service
    wasted = state.metrics.registry.get_sample_value("radarseg_rejected_requests_total",
                                                     {"model": "tiny", "reason": "quota_at_settlement"})
    assert wasted is None
    usage = client.get("/v1/usage", headers={"authorization": ACME}).json()["tenants"][0]
    assert usage["today"]["macs"] == billed * per_request <= usage["quota_macs"]
    assert usage["today"]["requests"] == billed
    assert usage["held"] == {"leases": 0, "macs": 0, "expired_leases": 0, "expired_macs": 0, "lease_seconds": 300.0}
    assert state.ledger.day_totals("acme").reserved_macs == 0  # every reservation settled or released


def test_first_reservation_covers_the_first_request(make_settings, client_for, cube_body):
    """the estimate from the warm-up alone (no billed request yet) is not below a request's cost."""
    client = client_for(make_settings())
    state = client.app.state.service
    served = state.pool.get("tiny")
    estimate = state.billing.estimate(served, "anonymous")
    r = client.post("/v1/segment", content=cube_body, headers=NPY)
    assert r.status_code == 200 and estimate >= r.json()["compute"]["macs"]["total"]


def test_ledger_equals_the_responses_after_concurrency_and_restart(make_settings, client_for, cube_body):
    settings = make_settings(api_keys=KEYS)
    client = client_for(settings)
    keys = [ACME, GLOBEX] * 5
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda key: client.post("/v1/segment", content=cube_body, headers=_auth(key)), keys))
    assert all(r.status_code == 200 for r in answers)
    expected = {}
    for r in answers:
        c = r.json()["compute"]
        tenant = r.json()["usage"]["tenant"]
        req, macs, us = expected.get(tenant, (0, 0, 0))
        expected[tenant] = (req + 1, macs + c["macs"]["total"], us + round(c["seconds"]["total"] * 1e6))

    def ledger_view(c) -> dict:
        tenants = c.get("/v1/usage?tenant=all", headers={"authorization": ADMIN}).json()["tenants"]
        return {t["tenant"]: (t["total"]["requests"], t["total"]["macs"], round(t["total"]["compute_seconds"] * 1e6))
                for t in tenants if t["total"]["requests"]}

    settings = settings.model_copy(update={"admin_tenants": ["ops"]})
    client.__exit__(None, None, None)  # stop the app: the ledger is a file
    restarted = client_for(settings)
    assert ledger_view(restarted) == expected
    ledger = restarted.app.state.service.ledger
    for tenant, (requests, macs, us) in expected.items():
        assert ledger.request_sums(tenant) == (requests, macs, us)


@pytest.fixture(params=["sqlite", "postgresql"])
def ledger_url_and_prefix(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'ledger.sqlite3'}", "radarseg_"
    return request.getfixturevalue("postgres_url"), request.getfixturevalue("pg_prefix")


def test_ledger_counts_exactly_from_many_threads_and_survives_reopening(ledger_url_and_prefix):
    url, prefix = ledger_url_and_prefix
    ledger = Ledger(url, table_prefix=prefix)
    ledger.create()
    day = dt.date(2030, 1, 2)

    def bill(i: int):
        return ledger.settle("acme" if i % 3 else "globex", model="m", macs=1000 + i, compute_us=7 * i, day=day)

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(bill, range(120)))
    ledger.dispose()
    reopened = Ledger(url, table_prefix=prefix)
    acme = [i for i in range(120) if i % 3]
    totals = reopened.day_totals("acme", day)
    assert (totals.requests, totals.macs, totals.compute_us) == (len(acme), sum(1000 + i for i in acme),
                                                                  sum(7 * i for i in acme))
    assert reopened.request_sums("acme") == (totals.requests, totals.macs, totals.compute_us)
    assert reopened.all_time(["globex"])["globex"].requests == 40
    reopened.dispose()


def test_reservations_never_let_the_billed_total_pass_the_limit(ledger_url_and_prefix):
    url, prefix = ledger_url_and_prefix
    ledger = Ledger(url, table_prefix=prefix)
    ledger.create()
    day, limit = dt.date(2030, 1, 3), 10_000

    def attempt(i: int) -> bool:
        estimate, actual = 900, 800 + 30 * (i % 7)  # some requests cost more than their reservation
        lease = ledger.reserve("acme", estimate, limit, day=day)
        if isinstance(lease, QuotaExceeded):
            return False
        return not isinstance(ledger.settle("acme", model="m", macs=actual, compute_us=1, lease=lease,
                                            limit=limit), QuotaExceeded)

    with ThreadPoolExecutor(8) as pool:
        billed = sum(pool.map(attempt, range(60)))
    totals = ledger.day_totals("acme", day)
    assert billed == totals.requests > 0
    assert totals.macs <= limit and totals.reserved_macs == 0
    assert ledger.request_sums("acme")[1] == totals.macs
    ledger.dispose()


def test_expired_leases_are_given_back_once(ledger_url_and_prefix):
    """A lease left by a request cut off by a crash blocks its tenant until its deadline, is then reclaimed by
    the next reservation, and is never given back twice (a late settle or release of it gives back nothing)."""
    url, prefix = ledger_url_and_prefix
    ledger = Ledger(url, table_prefix=prefix)
    ledger.create()
    day, limit = dt.date(2030, 1, 4), 1000
    t0 = dt.datetime(2030, 1, 4, 12, tzinfo=dt.UTC)
    cut_off = ledger.reserve("acme", 600, limit, lease_s=60, day=day, now=t0)
    assert not isinstance(cut_off, QuotaExceeded)
    blocked = ledger.reserve("acme", 600, limit, lease_s=60, day=day, now=t0 + dt.timedelta(seconds=30))
    assert isinstance(blocked, QuotaExceeded) and blocked.reserved_macs == 600
    assert ledger.held("acme", day, now=t0 + dt.timedelta(seconds=30)).leases == 1
    later = t0 + dt.timedelta(seconds=61)
    assert ledger.held("acme", day, now=later).expired_macs == 600
    lease = ledger.reserve("acme", 600, limit, lease_s=60, day=day, now=later)  # reclaims, then fits
    assert not isinstance(lease, QuotaExceeded) and ledger.day_totals("acme", day).reserved_macs == 600
    ledger.release(cut_off)  # the crashed request's lease is gone already: nothing more is given back
    assert ledger.day_totals("acme", day).reserved_macs == 600
    billed = ledger.settle("acme", model="m", macs=550, compute_us=1, lease=lease, limit=limit)
    assert not isinstance(billed, QuotaExceeded) and (billed.macs, billed.reserved_macs) == (550, 0)
    assert ledger.reclaim_expired(now=later + dt.timedelta(days=1)) == 0
    ledger.dispose()


def test_ledger_recent_maximum_survives_reopening(tmp_path):
    ledger = Ledger(f"sqlite:///{tmp_path / 'l.sqlite3'}")
    ledger.create()
    for macs in (5, 50, 20):
        ledger.settle("acme", model="m", macs=macs, compute_us=1)
    ledger.dispose()
    reopened = Ledger(f"sqlite:///{tmp_path / 'l.sqlite3'}")
    assert (reopened.recent_max_macs("m"), reopened.recent_max_macs("other")) == (50, 0)
    reopened.dispose()


def _billing(tmp_path, **settings):
    """A Billing on a SQLite ledger, and a stand-in for a served model (detector 1,000 MACs, warm-up segmenter
    10,000 MACs)."""
    from types import SimpleNamespace

    from service.accounting.billing import Billing
    from service.accounting.metrics import ServiceMetrics

    ledger = Ledger(f"sqlite:///{tmp_path / 'l.sqlite3'}")
    ledger.create()
    served = SimpleNamespace(spec=SimpleNamespace(name="m"), net=SimpleNamespace(detector_macs=lambda: 1000),
                             segment_macs_high=10_000)
    return Billing(ledger, Settings(data_dir=tmp_path, **settings), ServiceMetrics()), served


def test_the_estimate_is_the_tenants_own_and_a_refusal_never_raises_it(tmp_path):
    """the estimate was the maximum of every tenant's recent requests, and it rose with requests
    refused at settlement."""
    billing, served = _billing(tmp_path)
    ledger = billing.ledger
    assert billing.estimate(served, "globex") == 1000 + int(1.5 * 10_000)  # no history: the model's bound
    ledger.settle("acme", model="m", macs=8 * 10**9, compute_us=1)  # acme's outlier
    ledger.settle("globex", model="m", macs=9000, compute_us=1)
    assert billing.estimate(served, "globex") == 9000 and billing.estimate(served, "initech") == 16_000
    assert billing.estimate(served, "acme") == 8 * 10**9
    refused = ledger.settle("globex", model="m", macs=10**12, compute_us=1, limit=10**6)  # over its quota: not billed
    assert isinstance(refused, QuotaExceeded) and billing.estimate(served, "globex") == 9000
    ledger.dispose()


def test_admission_counts_every_affordable_request_and_retry_after_names_the_lease_deadline(tmp_path):
    """with quota for 6 requests in flight only 3 were admitted, and the 429 caused by the
    tenant's own leases said to wait until midnight."""
    from service.accounting.billing import quota_error, seconds_to_utc_midnight

    billing, served = _billing(tmp_path, tenant_quotas={"anonymous": 7 * 9000})
    ledger = billing.ledger
    ledger.settle("anonymous", model="m", macs=9000, compute_us=1)  # history: 9,000 a request; 6 more fit
    now = dt.datetime.now(dt.UTC)
    outcomes = [ledger.reserve("anonymous", billing.estimate(served, "anonymous"), 7 * 9000, lease_s=60 + i, now=now)
                for i in range(7)]
    assert [isinstance(o, QuotaExceeded) for o in outcomes] == [False] * 6 + [True]
    refused = outcomes[-1]
    assert refused.frees_at == outcomes[0].expires_at  # the first lease to end frees enough
    error = quota_error(refused, now=now)
    assert 59 <= int(error.headers["Retry-After"]) <= 61 and "in flight" in error.message
    assert billing.ledger.check("anonymous", 9000, 7 * 9000) is not None  # the same answer before the body
    for lease in outcomes[:6]:
        ledger.settle("anonymous", model="m", macs=9000, compute_us=1, lease=lease, limit=7 * 9000)
    spent = ledger.reserve("anonymous", 9000, 7 * 9000)
    assert isinstance(spent, QuotaExceeded) and spent.frees_at is None
    assert abs(int(quota_error(spent).headers["Retry-After"]) - seconds_to_utc_midnight()) <= 2
    ledger.dispose()


def test_a_quota_hold_is_given_back_on_any_way_out_but_settlement(tmp_path):
    """reserve on entering ``Billing.hold``, release on leaving it by an error or a cancellation."""
    import asyncio

    billing, served = _billing(tmp_path, daily_mac_quota=10**6)

    def reserved() -> int:
        return billing.ledger.day_totals("anonymous").reserved_macs

    async def failing() -> None:
        async with billing.hold("anonymous", served):
            assert reserved() == 16_000
            raise RuntimeError("inference failed")

    async def cancelled() -> None:
        inside = asyncio.Event()

        async def request() -> None:
            async with billing.hold("anonymous", served):
                inside.set()
                await asyncio.sleep(60)

        task = asyncio.create_task(request())
        await inside.wait()  # (a cancellation during the reservation itself leaves a lease that expires: lease_s)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    with pytest.raises(RuntimeError, match="inference failed"):
        asyncio.run(failing())
    assert reserved() == 0
    asyncio.run(cancelled())
    assert reserved() == 0 and billing.ledger.held("anonymous").leases == 0
    billing.ledger.dispose()


def test_compute_that_ran_is_billed_even_past_the_quota_and_the_next_request_is_refused(tmp_path):
    """a request admitted on its estimate that cost more than the quota had left ran for free (429 at settlement,
    nothing billed); now what ran is billed, and the tenant is refused from then on: at most one frame beyond."""
    import asyncio

    from models.erasenet.compute_report import FrameCompute
    from service.http.errors import ApiError

    billing, served = _billing(tmp_path, daily_mac_quota=20_000)  # the first estimate (16,000) fits

    async def one_request(macs: int):  # noqa: ANN202
        async with billing.hold("anonymous", served) as quota:
            compute = FrameCompute(detect_macs=1000, segment_macs=macs - 1000, segment_executed_macs=macs - 1000,
                                   detector_params=1, segmenter_params=1, seconds={"segment": 0.01})
            return await quota.settle(model="m", compute=compute, request_id=f"r{macs}")

    usage = asyncio.run(one_request(50_000))  # a crafted cube: 2.5x the quota's room
    assert usage.macs == 50_000 and usage.remaining_macs == 0
    totals = billing.ledger.day_totals("anonymous")
    assert totals.macs == 50_000 and totals.requests == 1 and totals.reserved_macs == 0
    with pytest.raises(ApiError) as refused:
        asyncio.run(one_request(1000))
    assert refused.value.status == 429
    billing.ledger.dispose()
