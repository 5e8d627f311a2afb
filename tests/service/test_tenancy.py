"""The service between tenants, against one real ``python -m service`` on loopback with small
limits: a fast start, header and cube value bounds, security headers, fair uploads, quotas that one tenant's cubes
or in-flight requests cannot turn against another, and connections that make no progress closed. Counts are small
and waits bounded by the 1-2 s limits set here; nothing asserts a time."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from service.accounting.billing import seconds_to_utc_midnight
from service.accounting.ledger import Ledger
from tests.service.conftest import NPY, GuardedServer, StartWatch, npy_bytes, server_env
from tests.service.raw_http import http_head, json_error, raw_exchange, read_answer

# One worker runs the whole module, in file order: the last test reads the refusals (header timeouts, 431) that the
# earlier ones caused on the module's server; split over pytest-xdist workers, it met a server that had seen none.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("tenancy")]

KEYS = {f"key-{name}-0123456789abcdef": name for name in ("acme", "globex", "hooli", "initech", "umbrella", "ops")}
AUTH = {tenant: {"authorization": f"Bearer {key}"} for key, tenant in KEYS.items()}
QUOTA = 10**10  # about 90 requests of the tiny model (1.1e8 MACs each)
OUTLIER = 10**13  # one huge billed cube of acme's, in the ledger before the server starts
LIMITS = {
    "RADARSEG_HEADER_TIMEOUT_S": "2", "RADARSEG_KEEP_ALIVE_S": "1", "RADARSEG_BODY_IDLE_S": "8",
    "RADARSEG_BODY_GRACE_S": "10", "RADARSEG_BODY_TIMEOUT_S": "12", "RADARSEG_MAX_BODY_BYTES": "10000000",
    "RADARSEG_MAX_TENANT_UPLOADS": "4", "RADARSEG_MAX_TENANT_UPLOAD_BYTES": "15000000",
    "RADARSEG_MAX_CONNECTIONS": "24",
    "RADARSEG_MAX_QUEUE": "4",
}


@pytest.fixture(scope="module")
def started(tiny_checkpoints, tmp_path_factory) -> Iterator[tuple]:
    """The server (keys for six tenants, three with quotas; acme's outlier billed before it starts), and what
    /healthz and /readyz answered while it was starting."""
    tmp = tmp_path_factory.mktemp("tenancy")
    ledger = Ledger(f"sqlite:///{tmp / 'data' / 'ledger.sqlite3'}")
    ledger.create()
    ledger.settle("acme", model="tiny", macs=OUTLIER, compute_us=1)
    ledger.dispose()
    env = server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(tmp / "data"), RADARSEG_API_KEYS=json.dumps(KEYS),
                     RADARSEG_ADMIN_TENANTS='["ops"]', RADARSEG_TENANT_QUOTAS=json.dumps(
                         {"globex": QUOTA, "hooli": QUOTA, "initech": QUOTA}), **LIMITS)
    process = GuardedServer(env, tmp / "server.log", log_level="info")
    try:
        seen = _watch_start(process.url, process.proc)
        process.wait_ready()
        yield process, seen, tmp / "data" / "ledger.sqlite3"
    finally:
        process.stop()


def _watch_start(url: str, proc) -> list[tuple[int, int, str]]:
    """(healthz status, readyz status, readyz status field) polled until ready (0: refused), or until the server
    exits or has used its start-up's CPU time (StartWatch: wall time is no deadline on a loaded machine)."""
    seen = []
    watch = StartWatch(proc.pid, cpu_s=150.0)
    with httpx.Client(timeout=5) as http:
        while proc.poll() is None and not watch.gave_up():
            try:
                health = http.get(f"{url}/healthz").status_code
                ready = http.get(f"{url}/readyz")
                seen.append((health, ready.status_code, ready.json().get("status", "")))
                if ready.status_code == 200:
                    break
            except httpx.HTTPError:
                seen.append((0, 0, ""))
            time.sleep(0.1)
    return seen


@pytest.fixture(scope="module")
def server(started):
    return started[0]


def test_healthz_answers_while_the_service_loads(started):
    """the port answers while the service imports and loads; /readyz says loading until ready."""
    _, seen, _ = started
    answered = [s for s in seen if s[0]]
    assert answered and answered[-1][1] == 200, seen
    loading = [s for s in answered if s[1] == 503]
    assert loading and all(health == 200 and status == "loading" for health, _, status in loading), seen
    log = started[0].log_path.read_text()
    assert "importing the service" in log and "model tiny: loading" in log and "model tiny ready" in log, log[-2000:]


def test_every_header_parser_bounds_digits_depth_and_size(server, cube_body):
    """an integer of 5,000 digits in X-Cube-Schema was a 500 (Python's digit limit)."""
    cases = [
        ('{"shape": [' + "9" * 5000 + "]}", 400, "number of 5000 characters"),
        ('{"shape": [' + "9" * 9000 + "]}", 422, "8192"),  # past the header's length bound (FastAPI's check)
        ('{"x": ' + "1" * 100 + "}", 400, "at most 64"),
        ('{"x": 1e' + "9" * 90 + "}", 400, "at most 64"),
    ]
    with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **AUTH["acme"]}) as http:
        for schema, status, message in cases:
            r = http.post("/v1/segment", content=cube_body, headers={"x-cube-schema": schema})
            assert r.status_code == status and message in r.text, (schema[:40], r.status_code, r.text[:300])
    status, headers, body = raw_exchange(server.port, [http_head("/v1/segment", {**NPY, **AUTH["acme"],
                                                                                "content-length": "9" * 5000})])
    json_error(status, headers, body, 400)


def test_values_beyond_float32_are_refused_and_never_billed(server, frame):
    """finite values too large for the float32 transform gave an empty 200, billed."""
    huge64 = frame.cube.copy()
    huge64[5, 5, 5] = 3e38 + 0j
    huge128 = frame.cube.astype(np.complex128)
    huge128[1, 2, 3] = 1e300
    log_power = np.full(frame.cube.shape, 40.0)
    log_power[0, 0, 0] = 1e300
    cases = [("/v1/segment", huge64, ("3e+38", "float32")), ("/v1/segment", huge128, ("1e+300", "float32")),
             ("/v1/segment?input=log_power", log_power, ("1e+300 dB", "at most 300 dB"))]
    with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **AUTH["umbrella"]}) as http:
        for url, cube, messages in cases:
            r = http.post(url, content=npy_bytes(cube))
            answer = json_error(r.status_code, r.headers, r.content, 422)
            assert all(message in answer["detail"] for message in messages), answer
        assert http.get("/v1/usage").json()["tenants"][0]["today"]["requests"] == 0


def test_security_headers_on_every_html_route_and_nosniff_everywhere(server):
    """/docs and /redoc had no CSP and could be framed; JSON routes sent no nosniff."""
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for page in ("/docs", "/redoc", "/viewer"):
            r = http.get(page)
            policy = r.headers.get("content-security-policy", "")
            assert r.status_code == 200 and "frame-ancestors 'none'" in policy, (page, policy)
            assert "unsafe-eval" not in policy and "script-src 'self'" in policy, (page, policy)
        answers = [http.get("/healthz"), http.get("/openapi.json"), http.get("/nowhere"), http.get("/v1/usage"),
                   http.get("/docs-assets/swagger-ui.css")]
    status, headers, _ = raw_exchange(server.port, [http_head("/v1/usage", {"x-junk": "a" * 70000}, method="GET")])
    assert status == 431 and headers["x-content-type-options"] == "nosniff"
    assert all(r.headers.get("x-content-type-options") == "nosniff" for r in answers), [
        (str(r.url), dict(r.headers)) for r in answers]


def test_quota_refusals_say_when_the_quota_frees_before_the_body_is_read(server, started, cube_body):
    """a 429 caused by the tenant's own requests in flight said to wait until midnight. Leases and
    billed MACs are written into the shared ledger as another process would; the 429s come without a body sent."""
    ledger = Ledger(f"sqlite:///{started[2]}")
    try:
        lease = ledger.reserve("hooli", QUOTA - 10**6, QUOTA, lease_s=20)
        ledger.settle("initech", model="tiny", macs=QUOTA - 10**6, compute_us=1)
        request = {**NPY, "content-length": str(len(cube_body))}
        status, headers, body = raw_exchange(server.port, [http_head("/v1/segment", {**request, **AUTH["hooli"]})])
        answer = json_error(status, headers, body, 429)
        assert 1 <= int(headers["retry-after"]) <= 21 and "in flight" in answer["detail"], (headers, answer)
        assert answer["used_macs"] == 0 and answer["reserved_macs"] == QUOTA - 10**6
        status, headers, body = raw_exchange(server.port, [http_head("/v1/segment", {**request, **AUTH["initech"]})])
        answer = json_error(status, headers, body, 429)
        assert abs(int(headers["retry-after"]) - seconds_to_utc_midnight()) <= 5 and "spent" in answer["detail"]
        ledger.release(lease)  # the request in flight ended: hooli is served
        r = httpx.post(f"{server.url}/v1/segment", content=cube_body, headers={**NPY, **AUTH["hooli"]}, timeout=60)
        assert r.status_code == 200, r.text
    finally:
        ledger.dispose()


def test_another_tenants_outlier_does_not_lock_a_tenant_out(server, cube_body):
    """acme's 1e13-MAC cube (billed before the start) made every tenant's estimate 1.5e13, so
    globex (quota 1e10) was refused every request."""
    with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **AUTH["globex"]}) as http:
        answers = [http.post("/v1/segment", content=cube_body) for _ in range(2)]
    assert [r.status_code for r in answers] == [200, 200], [r.text[:300] for r in answers]


def _hold(port: int, tenant: str, declared: int, sent: bytes) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sock.sendall(http_head("/v1/segment", {**NPY, **AUTH[tenant], "content-length": str(declared)}) + sent)
    return sock


def test_one_tenant_holding_uploads_leaves_another_served(server, cube_body):
    """8 empty uploads of one tenant made every other tenant's upload 503. A declared length no
    cube of the model can have is 413 at once; beyond its own bounds (4 uploads, 15 MB) a tenant is refused,
    chunked bodies included; another tenant is served meanwhile."""
    # (under the default max_body_bytes the 64 MiB + 64 KiB passes the global bound and is refused here)
    oversized = [_hold(server.port, "acme", 9_000_000, b"") for _ in range(10)]
    held = [_hold(server.port, "acme", len(cube_body), cube_body[:200]) for _ in range(3)]  # 12.6 MB of 15
    try:
        for sock in oversized:
            status, _, body = read_answer(sock)
            assert status == 413 and "at most 8398620 bytes" in json.loads(body)["detail"], body[:300]
        time.sleep(0.3)  # the held uploads are admitted
        chunked = [(http_head("/v1/segment", {**NPY, **AUTH["acme"], "transfer-encoding": "chunked"})
                    + b"%x\r\n" % 1000 + cube_body[:1000] + b"\r\n")]
        status, _, body = raw_exchange(server.port, chunked)
        assert status == 503 and "tenant 'acme' has uploads of" in json.loads(body)["detail"], body[:300]
        extra = [_hold(server.port, "acme", len(cube_body), cube_body[:200]) for _ in range(2)]
        for sock in extra:
            status, _, body = read_answer(sock)
            assert status == 503 and json.loads(body)["error"] == "uploads_saturated", body[:300]
            sock.close()
        with httpx.Client(base_url=server.url, timeout=60, headers={**NPY, **AUTH["globex"]}) as http:
            codes = [http.post("/v1/segment", content=cube_body).status_code for _ in range(3)]
        assert codes == [200] * 3
        for sock in held:  # then each held upload is cut off, silent for body_idle_s
            status, _, body = read_answer(sock)
            assert status == 408 and "silent for 8 s" in json.loads(body)["detail"], body[:300]
    finally:
        for sock in oversized + held:
            sock.close()


def _closed_within(sock: socket.socket, seconds: float, trickle: bytes = b"") -> bool:
    """Whether the server closes ``sock`` within ``seconds`` while we send ``trickle`` every 0.3 s."""
    deadline = time.monotonic() + seconds
    sock.settimeout(0.3)
    while time.monotonic() < deadline:
        try:
            if not sock.recv(65536):
                return True
        except TimeoutError:
            pass
        except ConnectionResetError:
            return True
        if trickle:
            try:
                sock.sendall(trickle)
            except (BrokenPipeError, ConnectionResetError):
                return True
    return False


def test_connections_making_no_progress_are_closed_whatever_they_sent(server):
    """GET /healthz announcing a megabyte, answered, then a byte now and then held the connection
    forever (each byte cancelled the keep-alive timer); so did blank lines between requests."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(http_head("/healthz", {"content-length": "1000000"}, method="GET") + b"x" * 200)
        status, headers, _ = read_answer(sock)
        assert status == 200 and headers["x-content-type-options"] == "nosniff"
        assert _closed_within(sock, 8, trickle=b"x")
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(http_head("/healthz", {}, method="GET"))
        assert read_answer(sock)[0] == 200
        assert _closed_within(sock, 8, trickle=b"\r\n")  # blank lines are no request head: 408 after 2 s
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(http_head("/healthz", {}, method="GET"))
        assert read_answer(sock)[0] == 200
        assert _closed_within(sock, 8)  # idle after an answer: keep_alive_s


def test_the_connection_cap_closes_the_longest_waiting_socket_and_refusals_are_counted(server):
    """40 quiet sockets against a cap of 24 leave a new client served; the server layer's
    refusals (evictions, header timeouts, 431) appear in /metrics."""
    # a head that never completes: closed with 408 after header_timeout_s (counted header_timeout), whatever the
    # earlier tests' blank-line trickle was classified as
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        assert _closed_within(sock, 8)
    # and a head too large, answered 431 (counted head_too_large) by this test itself, not read from an earlier one
    assert raw_exchange(server.port, [http_head("/v1/usage", {"x-junk": "a" * 70000}, method="GET")])[0] == 431
    quiet = []
    try:
        for _ in range(40):
            quiet.append(socket.create_connection(("127.0.0.1", server.port), timeout=10))
        time.sleep(0.3)
        with httpx.Client(base_url=server.url, timeout=10) as http:
            assert http.get("/healthz").status_code == 200
            closed = sum(_closed_within(sock, 0.05) for sock in quiet[:16])
            assert closed >= 10, closed  # the oldest were closed to make room
            metrics = http.get("/metrics", headers=AUTH["ops"]).text
    finally:
        for sock in quiet:
            sock.close()
    counts = {line.split("reason=\"")[1].split("\"")[0]: float(line.split()[-1]) for line in metrics.splitlines()
              if line.startswith("radarseg_server_refusals_total{")}
    assert counts.get("connection_evicted", 0) >= 10, counts
    assert counts.get("header_timeout", 0) >= 1 and counts.get("head_too_large", 0) >= 1, counts
