"""The service under abuse, against real ``python -m service`` processes on loopback: slow
uploaders, hostile heads and bodies, malformed HTTP, ambiguous credentials, the metrics' visibility, offline docs,
a busy port, kill -9 mid-request, and a bounded schemathesis run. Counts and waits are bounded; nothing asserts a
time."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import hypothesis
import pytest
import schemathesis
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from tests.service.conftest import KEYS, NPY, GuardedServer, server_env
from tests.service.raw_http import chunks, http_head, json_error, raw_exchange, read_answer

pytestmark = pytest.mark.slow

ACME_KEY, GLOBEX_KEY, ADMIN_KEY = KEYS
ACME = {"authorization": f"Bearer {ACME_KEY}"}
ADMIN = {"authorization": f"Bearer {ADMIN_KEY}"}
LIMITS = {  # small limits so that slow clients are cut off within seconds
    "RADARSEG_BODY_GRACE_S": "1", "RADARSEG_BODY_MIN_RATE": "65536", "RADARSEG_BODY_TIMEOUT_S": "4",
    "RADARSEG_MAX_UPLOADS": "14", "RADARSEG_MAX_TENANT_UPLOADS": "14", "RADARSEG_MAX_HEADER_BYTES": "16384",
    "RADARSEG_MAX_HEADERS": "50",
    "RADARSEG_HEADER_TIMEOUT_S": "3", "RADARSEG_WRITE_TIMEOUT_S": "2",
}


@pytest.fixture(scope="module")
def server(tiny_checkpoints, tmp_path_factory) -> Iterator:
    """One server with keys (acme, globex, admin ops), one model slot (replicas 1, queue 0) and small limits."""
    tmp = tmp_path_factory.mktemp("abuse")
    env = server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(tmp / "data"), RADARSEG_MAX_QUEUE="0",
                     RADARSEG_API_KEYS=json.dumps(KEYS), RADARSEG_ADMIN_TENANTS='["ops"]', **LIMITS)
    process = GuardedServer(env, tmp / "server.log")
    try:
        process.wait_ready()
        yield process
    finally:
        process.stop()


def test_slow_uploads_hold_no_model_slot_and_are_cut_off_with_408(server, cube_body):
    """Twelve clients trickling 1 KB each half second while the single model slot serves normal requests; each
    trickler is answered 408. before the fix a request took its slot before its body arrived: 9 slow uploads
    made every other request 503."""
    head = http_head("/v1/segment", {**NPY, **ACME, "content-length": str(len(cube_body))})
    slow: list[tuple[int, dict, bytes]] = []

    def trickle() -> None:
        slow.append(raw_exchange(server.port, [head, *chunks(cube_body[:40_000], 1024)], pause_s=0.5))

    threads = [threading.Thread(target=trickle) for _ in range(12)]
    for thread in threads:
        thread.start()
    time.sleep(0.5)  # the trickles have started
    with httpx.Client(base_url=server.url, timeout=60, headers=ACME) as http:
        normal = [http.post("/v1/segment", content=cube_body, headers=NPY).status_code for _ in range(4)]
    for thread in threads:
        thread.join(timeout=60)
    assert normal == [200] * 4
    assert len(slow) == 12
    for status, headers, body in slow:
        answer = json_error(status, headers, body, 408)
        assert answer["error"] == "body_timeout" and "minimum rate of 65536 bytes/s" in answer["detail"]
        assert headers["connection"] == "close"


def test_truncated_chunked_body_is_answered_408(server, cube_body):
    """A chunk announced as 4096 bytes, 300 sent, the connection left open: before the fix it got no answer."""
    head = http_head("/v1/segment", {**NPY, **ACME, "transfer-encoding": "chunked"})
    status, headers, body = raw_exchange(server.port, [head + b"1000\r\n" + cube_body[:300]])
    answer = json_error(status, headers, body, 408)
    assert answer["error"] == "body_timeout" and headers["connection"] == "close"


def test_a_head_trickled_byte_by_byte_is_cut_off_with_408(server):
    """Slow headers (before the app sees a request): one byte each half second, answered 408 once the head is
    not complete within header_timeout_s; the server still answers others."""
    head = http_head("/v1/usage", ACME, method="GET")
    status, headers, body = raw_exchange(server.port, [head[i:i + 1] for i in range(len(head))], pause_s=0.5)
    answer = json_error(status, headers, body, 408)
    assert "request head not complete within 3 s" in answer["detail"]
    assert httpx.get(f"{server.url}/healthz", timeout=30).status_code == 200


def test_uploads_beyond_the_bound_are_503_with_retry_after(server, cube_body):
    head = http_head("/v1/segment", {**NPY, **ACME, "content-length": str(len(cube_body))})
    socks = []
    try:
        for _ in range(14):  # max_uploads: every place taken by a body that is not coming
            sock = socket.create_connection(("127.0.0.1", server.port), timeout=30)
            sock.sendall(head + cube_body[:200])
            socks.append(sock)
        time.sleep(0.3)  # the server has read the heads
        r = httpx.post(f"{server.url}/v1/segment", content=cube_body, headers={**NPY, **ACME}, timeout=60)
        answer = json_error(r.status_code, r.headers, r.content, 503)
        assert answer["error"] == "uploads_saturated" and int(r.headers["retry-after"]) >= 1
        for sock in socks:  # then each of them is cut off
            assert read_answer(sock)[0] == 408
    finally:
        for sock in socks:
            sock.close()
    assert httpx.post(f"{server.url}/v1/segment", content=cube_body, headers={**NPY, **ACME},
                      timeout=60).status_code == 200


def _npy_with_header_text(text: str) -> bytes:
    encoded = text.encode("latin1")
    return b"\x93NUMPY\x02\x00" + len(encoded).to_bytes(4, "little") + encoded


HOSTILE_HEADS: dict[str, tuple[bytes, int]] = {
    # (request bytes, expected status); every answer is a JSON error
    "32 MiB header": (http_head("/v1/segment", {**NPY, **ACME, "x-junk": "a" * (32 << 20)}), 431),
    "5000 headers": (http_head("/v1/segment", {**NPY, **ACME, **{f"x-h{i}": "v" for i in range(5000)}}), 431),
    "1 MB query string": (http_head("/v1/usage?" + "a=b&" * 250_000, ACME, method="GET"), 414),
    "bad Content-Length": (http_head("/v1/segment", {**NPY, **ACME, "content-length": "12x"}), 400),
    "duplicated Content-Length": (http_head("/v1/segment", {**NPY, **ACME, "content-length": "10"})[:-2]
                                  + b"Content-Length: 20\r\n\r\n" + b"x" * 20, 400),
    "Content-Length beside chunked": (http_head("/v1/segment", {**NPY, **ACME, "content-length": "10",
                                                            "transfer-encoding": "chunked"}) + b"0\r\n\r\n", 400),
    "bad chunk size": (http_head("/v1/segment", {**NPY, **ACME, "transfer-encoding": "chunked"})
                       + b"zz\r\nabc\r\n", 400),
}


@pytest.mark.parametrize("case", list(HOSTILE_HEADS))
def test_hostile_http_is_answered_in_json_and_the_server_stays_up(server, case):
    request, expected = HOSTILE_HEADS[case]
    status, headers, body = raw_exchange(server.port, chunks(request, 16384))
    json_error(status, headers, body, expected)
    assert httpx.get(f"{server.url}/healthz", timeout=30).status_code == 200


def test_hostile_bodies_and_headers_are_4xx(server, cube_body, frame):
    """The two former 500s (a .npy header of 60,000 minus signs, an X-Cube-Schema of 4,000 nested brackets)
    and their relatives, each a 400 naming the problem."""
    cases = [
        ({}, _npy_with_header_text("-" * 60000 + "1"), "oversized .npy header"),
        ({}, _npy_with_header_text("-" * 5000 + "1"), "sign characters"),
        ({}, _npy_with_header_text("[" * 4000 + "]" * 4000), "nested 4000 deep"),
        ({"x-cube-schema": "[" * 4000 + "]" * 4000}, cube_body, "X-Cube-Schema is nested 4000 levels deep"),
        ({"x-cube-schema": '{"a": ' * 17 + "1" + "}" * 17}, cube_body, "at most 16"),
        ({"x-cube-schema": "{nope"}, cube_body, "X-Cube-Schema is not valid JSON"),
    ]
    with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **ACME}) as http:
        for headers, body, message in cases:
            r = http.post("/v1/segment", content=body, headers=headers)
            assert r.status_code == 400 and message in r.json()["detail"], (message, r.status_code, r.text[:300])


def test_ambiguous_credentials_are_refused(server, cube_body):
    both = [("x-api-key", ACME_KEY), ("authorization", "Basic dXNlcjpwYXNz")]
    cases = {
        "two X-API-Key": [("x-api-key", ACME_KEY), ("x-api-key", GLOBEX_KEY)],
        "X-API-Key beside Basic": both,
        "X-API-Key beside Bearer": [("x-api-key", ACME_KEY), ("authorization", f"Bearer {ACME_KEY}")],
    }
    with httpx.Client(base_url=server.url, timeout=60) as http:
        for name, headers in cases.items():
            for method, path in (("POST", "/v1/segment"), ("GET", "/v1/usage"), ("GET", "/metrics")):
                r = http.request(method, path, headers=[*headers, ("content-type", NPY["content-type"])],
                                 content=cube_body if method == "POST" else None)
                assert r.status_code == 400 and r.json()["error"] == "ambiguous_credentials", (name, path, r.text)
        assert http.get("/v1/usage", headers={"x-api-key": ACME_KEY}).status_code == 200


def test_metrics_need_an_admin_key(server, cube_body):
    assert httpx.post(f"{server.url}/v1/segment", content=cube_body, headers={**NPY, **ACME},
                      timeout=60).status_code == 200
    with httpx.Client(base_url=server.url, timeout=30) as http:
        assert http.get("/metrics").status_code == 401
        refused = http.get("/metrics", headers=ACME)
        assert refused.status_code == 403 and 'tenant="acme"' not in refused.text
        assert 'radarseg_macs_total{model="tiny",tenant="acme"}' in http.get("/metrics", headers=ADMIN).text


def test_product_path_segment_is_the_same_operation(server, cube_body):
    with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **ACME}) as http:
        alias, main = http.post("/segment", content=cube_body), http.post("/v1/segment", content=cube_body)
    assert alias.status_code == main.status_code == 200
    assert alias.json()["compute"]["macs"] == main.json()["compute"]["macs"]
    assert alias.json()["usage"]["requests"] == main.json()["usage"]["requests"] - 1


def test_docs_and_redoc_load_their_assets_from_the_service(server):
    with httpx.Client(base_url=server.url, timeout=30) as http:
        pages = {"/docs": ("swagger-ui-bundle.js", "swagger-ui.css"), "/redoc": ("redoc.standalone.js",)}
        for page, assets in pages.items():
            html = http.get(page).text
            sources = [part.split('"')[1] for part in html.split("src=")[1:]] + \
                      [part.split('"')[1] for part in html.split("href=")[1:]]
            assert sources and all(src.startswith("/") for src in sources), (page, sources)  # nothing from elsewhere
            for asset in assets:
                url = next(src for src in sources if src.endswith(asset))
                r = http.get(url)
                assert r.status_code == 200 and len(r.content) > 10_000, (url, r.status_code)


def test_a_second_server_on_a_busy_port_fails_before_loading_models(server, tiny_checkpoints, tmp_path):
    second = GuardedServer(server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(tmp_path / "data")),
                           tmp_path / "second.log", port=server.port, log_level="info")
    try:
        code = second.proc.wait(timeout=120)
    finally:
        second.stop()
    log = Path(second.log_path).read_text()
    assert code == 2 and "cannot bind" in log, log[-2000:]
    assert "model tiny ready" not in log and "Waiting for application startup" not in log, log[-2000:]


CONFORMANCE = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance,
               response_headers_conformance]


def test_schemathesis_finds_no_server_error_and_no_schema_mismatch(server):
    """A bounded property-based run over every operation of the OpenAPI document, with the admin's key unless
    the case brings its own credentials: no 5xx, and every answer as documented (status, type, body, headers).
    (Driven through hypothesis directly: schemathesis' pytest plugin does not run under pytest 9.)"""
    schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
    failures: dict[str, str] = {}
    operations = [result.ok() for result in schema.get_all_operations()]
    for operation in operations:

        @hypothesis.given(case=operation.as_strategy())
        @hypothesis.settings(max_examples=15, deadline=None, database=None, derandomize=True,
                             suppress_health_check=list(hypothesis.HealthCheck), phases=[hypothesis.Phase.generate])
        def conforms(case: schemathesis.Case) -> None:
            own = {name.lower() for name in (case.headers or {})} & {"x-api-key", "authorization"}
            case.call_and_validate(headers={} if own else ADMIN, checks=CONFORMANCE, timeout=60)

        try:
            conforms()
        except Exception as exc:  # noqa: BLE001 (collect every operation's failure, then report them all)
            failures[operation.label] = f"{type(exc).__name__}: {str(exc)[:1500]}"
    assert len(operations) >= 6 and not failures, failures


def test_a_client_that_stops_reading_its_answer_is_cut_off_after_the_write_timeout(server):
    """An answer of several MB to a client that never reads: the server's buffer fills, and the connection is cut
    once the write timeout has passed since it stopped taking the answer (the answer is not held for ever)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connecting: a small window
        sock.connect(("127.0.0.1", server.port))
        sock.sendall(http_head("/v1/examples/1", ACME, method="GET"))
        time.sleep(2 + 3)  # the write timeout (2 s) and margin, reading nothing
        sock.settimeout(10)
        received, started = 0, time.monotonic()
        try:
            while chunk := sock.recv(65536):
                received += len(chunk)
        except (ConnectionResetError, TimeoutError):
            pass
        assert time.monotonic() - started < 10
    length = len(httpx.get(f"{server.url}/v1/examples/1", headers=ACME, timeout=30).content)
    assert length > 1_000_000 and received < length  # cut before the whole answer was taken
    metrics = httpx.get(f"{server.url}/metrics", headers=ADMIN, timeout=30).text
    assert 'radarseg_server_refusals_total{reason="write_timeout"}' in metrics

