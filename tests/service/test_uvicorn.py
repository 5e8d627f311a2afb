"""Against real ``radarseg serve`` (uvicorn) processes on loopback, started and stopped by the tests:
a simulated cube, bad input over real HTTP, a restart on a SQLite ledger, and two API processes
sharing one PostgreSQL ledger."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.accounting.ledger import Ledger
from service.settings import REPO_ROOT, Settings, resolve_path
from tests.service.conftest import NPY, npy_bytes, server_env

pytestmark = pytest.mark.slow


def _post_many(urls: list[str], body: bytes, n: int) -> list[httpx.Response]:
    with httpx.Client(timeout=120) as http, ThreadPoolExecutor(4) as pool:
        return list(pool.map(lambda i: http.post(f"{urls[i % len(urls)]}/v1/segment", content=body, headers=NPY),
                             range(n)))


def _sums(answers: list[httpx.Response]) -> tuple[int, int, int]:
    bodies = [r.json() for r in answers]
    return (len(bodies), sum(b["compute"]["macs"]["total"] for b in bodies),
            sum(round(b["compute"]["seconds"]["total"] * 1e6) for b in bodies))


def test_real_server_segments_refuses_bad_input_and_keeps_its_ledger_across_a_restart(
        serve, tiny_checkpoints, tmp_path, cube_body, frame):
    env = server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(tmp_path / "data"), RADARSEG_MAX_BODY_BYTES="8000000")
    with serve(env) as (server,):
        with httpx.Client(base_url=server.url, timeout=60) as http:
            r = http.post("/v1/segment?outputs=objects,masks", content=cube_body, headers=NPY)
            assert r.status_code == 200 and r.json()["compute"]["macs"]["total"] == int(r.headers["x-compute-macs"])
            bad = {
                400: npy_bytes(np.array([None, {"x": 1}], dtype=object), allow_pickle=True),
                413: cube_body + b"\0" * 4_000_000,
                422: npy_bytes(frame.cube[:, :, :16]),
            }
            for status, body in bad.items():
                assert http.post("/v1/segment", content=body, headers=NPY).status_code == status
            assert http.post("/v1/segment", content=cube_body, headers={"content-type": "image/png"}).status_code == 415
            assert http.get("/healthz").status_code == 200
        answers = [r, *_post_many([server.url], cube_body, 6)]
        assert all(a.status_code == 200 for a in answers)
        assert 'radarseg_segment_requests_total{model="tiny",tenant="anonymous"} 7.0' in httpx.get(
            f"{server.url}/metrics").text
    requests, macs, compute_us = _sums(answers)
    with serve(env) as (server,):  # same SQLite file, new process
        usage = httpx.get(f"{server.url}/v1/usage").json()["tenants"][0]["total"]
        assert (usage["requests"], usage["macs"], round(usage["compute_seconds"] * 1e6)) == (requests, macs, compute_us)


def test_two_api_processes_share_one_postgresql_ledger(serve, tiny_checkpoints, postgres_url, pg_prefix, cube_body):
    env = server_env(tiny_checkpoints, RADARSEG_LEDGER_URL=postgres_url, RADARSEG_LEDGER_TABLE_PREFIX=pg_prefix,
                     RADARSEG_DAILY_MAC_QUOTA=str(10**15))
    with serve(env, env) as servers:
        answers = _post_many([s.url for s in servers], cube_body, 12)
        assert all(a.status_code == 200 for a in answers), [a.text for a in answers if a.status_code != 200]
        requests, macs, compute_us = _sums(answers)
        for server in servers:  # both processes read the same totals
            usage = httpx.get(f"{server.url}/v1/usage").json()["tenants"][0]
            assert (usage["total"]["requests"], usage["total"]["macs"]) == (requests, macs)
            assert round(usage["total"]["compute_seconds"] * 1e6) == compute_us
    ledger = Ledger(postgres_url, table_prefix=pg_prefix, pool_size=0)
    totals = ledger.day_totals("anonymous")
    assert (totals.requests, totals.macs, totals.compute_us, totals.reserved_macs) == (requests, macs, compute_us, 0)
    assert ledger.request_sums("anonymous") == (requests, macs, compute_us)
    ledger.dispose()


def test_shipped_model_finds_the_simulated_objects(make_settings, client_for):
    """The default settings serve the shipped checkpoints; a simulated cube's objects are found where the
    simulator put them."""
    spec = Settings().models[0]
    if not (resolve_path(spec.detector).is_file() and resolve_path(spec.segmenter).is_file()):
        pytest.skip(f"no shipped checkpoints under {REPO_ROOT / Path(spec.detector).parent} yet")
    from radar.simulate import simulate_sequence

    client = client_for(make_settings(models=[spec]))
    found = truth = 0
    for frame in simulate_sequence("small", 3, seed=123):
        r = client.post("/v1/segment", content=npy_bytes(frame.cube), headers=NPY)
        assert r.status_code == 200, r.text
        objects = r.json()["objects"]
        for target in (o for o in frame.objects if o.n_voxels >= 20):
            truth += 1
            found += any(np.hypot(o["x"] - target.centre_x, o["y"] - target.centre_y) < 3.0 for o in objects)
    assert truth > 0 and found / truth >= 0.6, (found, truth)
