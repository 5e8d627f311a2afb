"""Examples under load and with hostile radars: 30 concurrent requests simulate each example once and stay within
300 MB; a radar's name reaches Content-Disposition only as a slug and an RFC 6266 ``filename*``; a radar with
classes the simulator does not know answers 404 ``no_examples`` (not a 500)."""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import unquote

import numpy as np

from service.example_cache import ExampleCache
from service.routes.examples import EXAMPLE_SEEDS, attachment


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _set_profile(client, **changes) -> None:
    net = client.app.state.service.pool.models["tiny"].nets[0]
    net.profile = dataclasses.replace(net.profile, **changes)


def test_thirty_concurrent_example_requests_simulate_each_example_once_within_300_mb(make_settings, client_for):
    client = client_for(make_settings(warmup=False))
    paths = [f"/v1/examples/{1 + i % len(EXAMPLE_SEEDS)}?frame={i % 10}" for i in range(27)]
    paths += ["/v1/examples"] * 3
    peak, done = [_rss_mb()], threading.Event()
    before = peak[0]

    def sample() -> None:
        while not done.is_set():
            peak.append(_rss_mb())
            time.sleep(0.02)

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        with ThreadPoolExecutor(30) as pool:
            answers = list(pool.map(client.get, paths))
    finally:
        done.set()
        sampler.join()
    assert all(a.status_code == 200 for a in answers), [a.text[:200] for a in answers if a.status_code != 200]
    assert client.app.state.service.examples.simulations == len(EXAMPLE_SEEDS)  # one per example
    print(f"30 concurrent example requests: RSS {before:.0f} MB before, peak {max(peak):.0f} MB")
    assert max(peak) - before <= 300


def test_the_cache_keeps_within_its_budget_and_simulates_again_only_what_it_let_go():
    from radar.profiles import resolve_profile

    cache = ExampleCache(max_bytes=50 * 2**20, frames=2)  # one sequence of 2 small frames is 8 MiB
    profile = resolve_profile("small")
    first = cache.get(profile, 2)
    assert cache.get(profile, 2) is first and cache.simulations == 1
    for seed in range(20, 27):
        cache.get(profile, seed)
    assert sum(s.nbytes for s in cache._kept.values()) <= 50 * 2**20
    cache.get(profile, 2)
    assert cache.simulations == 9  # let go under the budget, made again


def test_a_hostile_radar_name_reaches_content_disposition_as_a_slug_and_filename_star(make_settings, client_for):
    client = client_for(make_settings(warmup=False))
    hostile = 'q"; filename="evil.html\r\nX-Forged: 1/../../é'
    _set_profile(client, name=hostile)
    r = client.get("/v1/examples/1?frame=1")
    assert r.status_code == 200, r.text
    disposition = r.headers["content-disposition"]
    assert "x-forged" not in r.headers and disposition.count("filename=") == 1
    plain = disposition.split('filename="', 1)[1].split('"', 1)[0]
    assert plain.isascii() and "/" not in plain and '"' not in plain and plain.endswith("-frame-1.npy")
    encoded = disposition.split("filename*=UTF-8''", 1)[1]
    assert unquote(encoded) == f"example-1-{hostile.replace('/', '_')}-frame-1.npy"
    assert all(c.isalnum() or c in "%-._~" for c in encoded)
    np.load(__import__("io").BytesIO(r.content))


def test_attachment_is_rfc_6266():
    assert attachment("example-1-small.npy") == ("attachment; filename=\"example-1-small.npy\"; "
                                                 "filename*=UTF-8''example-1-small.npy")
    assert attachment("räder.npy").endswith("filename*=UTF-8''r%C3%A4der.npy")


def test_a_radar_with_classes_the_simulator_does_not_know_has_no_examples(make_settings, client_for):
    client = client_for(make_settings(warmup=False))
    _set_profile(client, class_names=("pedestrian", "hovercraft\r\nforged", "car"))
    for path in ("/v1/examples", "/v1/examples/2"):
        r = client.get(path)
        assert r.status_code == 404 and r.json()["error"] == "no_examples", r.text
        assert "hovercraft\\r\\nforged" in r.json()["detail"]
