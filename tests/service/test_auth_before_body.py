"""Authentication before any body is read: a keyless 64 MiB JSON body to ``POST /v1/streams`` is a 401 with the
server's memory unchanged (a real uvicorn process), no route lets FastAPI read a body before its dependencies, and
a keyed JSON body past ``max_json_body_bytes`` is a 413."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from fastapi.routing import APIRoute

from tests.service.conftest import KEYS, GuardedServer, server_env
from tests.service.raw_http import chunks, http_head, json_error, raw_exchange

KEY = next(iter(KEYS))


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_no_route_reads_a_body_before_its_dependencies(make_settings):
    """FastAPI reads a declared Body() parameter before it resolves any dependency (the key check among them):
    routes that take a body read it themselves after authentication (service.inputs.json_body,
    service.inputs.upload)."""
    from service.main import create_app

    app = create_app(make_settings(api_keys=KEYS))
    readers = [route.path for route in app.routes if isinstance(route, APIRoute) and route.body_field is not None]
    assert readers == [], f"routes whose body FastAPI reads before the key is checked: {readers}"


def test_a_keyed_json_body_past_the_limit_is_a_413_and_a_bad_one_a_422(make_settings, client_for):
    client = client_for(make_settings(api_keys=KEYS, warmup=False, max_json_body_bytes=1024))
    auth = {"authorization": f"Bearer {KEY}"}
    json_type = {**auth, "content-type": "application/json"}
    big = client.post("/v1/streams", content=json.dumps({"model": "x" * 2000}), headers=json_type)
    assert big.status_code == 413 and "max_json_body_bytes" in big.json()["detail"], big.text
    bad = client.post("/v1/streams", json={"model": "tiny", "extra": 1}, headers=auth)
    assert bad.status_code == 422 and bad.json()["error"] == "invalid_parameters", bad.text
    assert client.post("/v1/streams", content=b"{}", headers={**auth, "content-type": "text/plain"}).status_code == 415
    assert client.post("/v1/streams", json={"model": "tiny"}, headers=auth).status_code == 201
    assert client.post("/v1/streams", headers=auth).status_code == 201  # no body: the default model


@pytest.mark.slow
def test_a_keyless_64_mib_json_body_is_refused_before_it_is_read(tiny_checkpoints, tmp_path):
    env = server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(tmp_path / "data"), RADARSEG_WARMUP="false",
                     RADARSEG_API_KEYS=json.dumps(KEYS))
    server = GuardedServer(env, tmp_path / "server.log")
    try:
        server.wait_ready()
        body = b'{"model": "' + b"x" * (64 * 2**20 - 16) + b'"}'
        before = _rss_mb(server.proc.pid)
        for headers in ({"content-type": "application/json", "content-length": str(len(body))},
                        {"content-type": "application/json", "transfer-encoding": "chunked"}):
            pieces = chunks(body, 2**20)
            if "transfer-encoding" in headers:
                pieces = [b"%x\r\n%s\r\n" % (len(p), p) for p in pieces] + [b"0\r\n\r\n"]
            status, answer_headers, answer = raw_exchange(server.port, [http_head("/v1/streams", headers), *pieces])
            assert json_error(status, answer_headers, answer, 401)["error"] == "unauthorized"
        after = _rss_mb(server.proc.pid)
        print(f"server RSS before {before:.1f} MB, after two keyless 64 MiB JSON bodies {after:.1f} MB")
        assert after - before < 50, f"RSS went from {before:.0f} MB to {after:.0f} MB"
    finally:
        server.stop()
