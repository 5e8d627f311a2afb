"""The service when its usage ledger's database fails: a real PostgreSQL behind a TCP proxy (tests/service/tcp_proxy.py)
that the test cuts (the database is gone) and turns into a black hole (connections accepted, nothing answered),
and a SQLite ledger whose file another process holds locked.

What a client sees: 503 with ``ledger_unavailable`` (never a 500, never a hung request: at most 10 s), ``/healthz``
within a second throughout (on a loaded machine: twice what it took beside the same requests before the fault),
``/readyz`` 503 within 5 s of the fault and 200 within 10 s of recovery, a tenant with quota left served at once
after it (no lease left behind), and as many ledger rows as answers of 200.
"""

from __future__ import annotations

import sqlite3
import time
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlsplit, urlunsplit

import pytest
from sqlalchemy import func, select

from tests.service.conftest import NPY
from tests.service.tcp_proxy import TcpProxy

pytestmark = pytest.mark.slow  # seconds of faults each (make test runs them; make test-fast does not)

KEY = "fault-test-key-0123456789"
TENANT = "acme"


@pytest.fixture
def proxy(postgres_url):
    parts = urlsplit(postgres_url)
    tcp = TcpProxy(parts.hostname or "127.0.0.1", parts.port or 5432).start()
    yield tcp
    tcp.close()


def _through(postgres_url: str, port: int) -> str:
    parts = urlsplit(postgres_url)
    user = f"{parts.username}@" if parts.username else ""
    return urlunsplit((parts.scheme, f"{user}127.0.0.1:{port}", parts.path, parts.query, parts.fragment))


def _settings(make_settings, url: str, prefix: str):
    return make_settings(ledger_url=url, ledger_table_prefix=prefix, api_keys={KEY: TENANT},
                         daily_mac_quota=10**15, ledger_timeout_s=2.0, ledger_check_s=0.5)


def _timed(call):
    started = time.monotonic()
    answer = call()
    return answer, time.monotonic() - started


def _wait_for(predicate, timeout_s: float) -> float:
    """Seconds until ``predicate()`` is true (AssertionError after ``timeout_s``)."""
    started = time.monotonic()
    while not predicate():
        assert time.monotonic() - started < timeout_s, f"not within {timeout_s} s"
        time.sleep(0.2)
    return time.monotonic() - started


def _busy(client, cube_body, auth) -> tuple[list, list]:
    """Four /v1/usage and two /v1/segment requests in flight, and three /healthz timed meanwhile: (answers, health),
    each a list of (response, seconds)."""
    with ThreadPoolExecutor(6) as pool:
        usage = [pool.submit(_timed, lambda: client.get("/v1/usage", headers=auth)) for _ in range(4)]
        segment = [pool.submit(_timed, lambda: client.post("/v1/segment", content=cube_body, headers={**NPY, **auth}))
                   for _ in range(2)]
        health = [_timed(lambda: client.get("/healthz")) for _ in range(3)]
        return [f.result() for f in usage + segment], health


def _health_limit_s(client, cube_body, auth) -> float:
    """How long /healthz may take during a fault: 1 s, or on a loaded machine twice what it took here beside the same
    requests with the ledger up (measured, so that load alone never fails the check; a /healthz that waited for the
    ledger would take its 2 s timeout more)."""
    answers, health = _busy(client, cube_body, auth)
    assert all(answer.status_code == 200 for answer, _ in answers), [a.text for a, _ in answers]
    assert all(r.status_code == 200 for r, _ in health), health
    return max(1.0, 2 * max(seconds for _, seconds in health))


def _fault_checks(client, cube_body, auth, health_limit_s: float) -> None:
    """During a fault: /readyz 503 within 5 s, 503s (not 5xx else) within 10 s, /healthz within its limit."""
    _wait_for(lambda: client.get("/readyz").status_code == 503, 5)
    assert "ledger" in client.get("/readyz").json() and client.get("/readyz").json()["ledger"]
    answers, health = _busy(client, cube_body, auth)
    for answer, seconds in answers:
        assert answer.status_code == 503 and answer.json()["error"] == "ledger_unavailable", answer.text
        assert seconds < 10
    assert all(r.status_code == 200 and seconds < health_limit_s for r, seconds in health), (health, health_limit_s)


def test_postgresql_cut_then_black_holed_then_back(make_settings, client_for, postgres_url, pg_prefix, proxy,
                                                   cube_body):
    client = client_for(_settings(make_settings, _through(postgres_url, proxy.port), pg_prefix))
    auth = {"Authorization": f"Bearer {KEY}"}
    state = client.app.state.service
    ok = 0

    def serve_one() -> None:
        nonlocal ok
        r = client.post("/v1/segment", content=cube_body, headers={**NPY, **auth})
        assert r.status_code == 200, r.text
        ok += 1

    serve_one()
    health_limit_s = _health_limit_s(client, cube_body, auth)
    ok += 2  # its two segment requests
    for fault in ("down", "hole"):
        proxy.set_mode(fault)
        _fault_checks(client, cube_body, auth, health_limit_s)
        proxy.set_mode("forward")
        _wait_for(lambda: client.get("/readyz").status_code == 200, 10)
        serve_one()  # at once: no lease left behind holds the tenant's quota
        usage = client.get("/v1/usage", headers=auth)
        assert usage.status_code == 200 and usage.json()["tenants"][0]["held"]["leases"] == 0, usage.text
    ledger = state.ledger
    with ledger.engine.connect() as conn:
        rows = conn.execute(select(func.count()).select_from(ledger.requests)
                            .where(ledger.requests.c.tenant == TENANT)).scalar_one()
    assert rows == ok == 5


def test_the_service_starts_without_its_database_and_becomes_ready_when_it_returns(make_settings, client_for,
                                                                                   postgres_url, pg_prefix, proxy,
                                                                                   cube_body):
    proxy.set_mode("down")
    client = client_for(_settings(make_settings, _through(postgres_url, proxy.port), pg_prefix))
    assert client.get("/readyz").status_code == 503 and client.get("/healthz").status_code == 200
    refused = client.post("/v1/segment", content=cube_body, headers={**NPY, "Authorization": f"Bearer {KEY}"})
    assert refused.status_code == 503
    proxy.set_mode("forward")
    _wait_for(lambda: client.get("/readyz").status_code == 200, 10)
    served = client.post("/v1/segment", content=cube_body, headers={**NPY, "Authorization": f"Bearer {KEY}"})
    assert served.status_code == 200, served.text


def test_a_locked_sqlite_ledger_is_a_503_and_then_served_again(make_settings, client_for, cube_body, tmp_path):
    client = client_for(make_settings(api_keys={KEY: TENANT}, daily_mac_quota=10**15, ledger_timeout_s=1.0,
                                      ledger_check_s=0.5, data_dir=tmp_path / "locked"))
    auth = {**NPY, "Authorization": f"Bearer {KEY}"}
    assert client.post("/v1/segment", content=cube_body, headers=auth).status_code == 200
    holder = sqlite3.connect(tmp_path / "locked" / "ledger.sqlite3", timeout=1, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")  # another process writing, for longer than the ledger timeout
    try:
        refused, seconds = _timed(lambda: client.post("/v1/segment", content=cube_body, headers=auth))
        assert refused.status_code == 503 and refused.json()["error"] == "ledger_unavailable" and seconds < 10
        assert client.get("/healthz").status_code == 200
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    _wait_for(lambda: client.post("/v1/segment", content=cube_body, headers=auth).status_code == 200, 10)
