"""GET /viewer: the page served by the API, in a real browser (Debian's ``chromium``, headless) against a real
``radarseg serve`` on loopback: example 1 drawn on both views with its objects and MACs, and a bad file
answered with the service's own message. The browser and the server are stopped by pid."""

from __future__ import annotations

import base64
import os
from pathlib import Path
from urllib.parse import quote

import httpx
import numpy as np
import pytest

from service.encoding import decode_array
from tests.browser import CHROMIUM, Dom, settled_html
from tests.service.conftest import NPY

# .ci/run installs chromium and sets RADARSEG_REQUIRE_BROWSER=1: there a missing browser fails the test.
REQUIRED = os.environ.get("RADARSEG_REQUIRE_BROWSER") == "1"
SETTLED = "['done', 'error'].includes(document.body.dataset.state)"  # what the page says once it has an answer
pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None and not REQUIRED,
                                                   reason="chromium is not installed (.ci/run installs it)")]


def rendered(url: str, profile: Path) -> Dom:
    """The page once it has settled (``done`` or ``error``), waited on in real time (tests/browser.py)."""
    return Dom(settled_html(url, profile, SETTLED))


@pytest.fixture
def server(serve, tmp_path):
    """``radarseg serve`` with the default settings: the shipped model (the tiny random one finds no object to
    list). No warm-up (three scenes segmented at start-up for the quota estimate; no quota here)."""
    assert CHROMIUM is not None, "chromium is not installed: apt-get install -y chromium (.ci/run does)"
    with serve({"RADARSEG_DATA_DIR": str(tmp_path / "data"), "RADARSEG_WARMUP": "false"}) as (server,):
        yield server


def test_viewer_draws_an_example_and_shows_the_services_error_messages(server, tmp_path):
    with httpx.Client(base_url=server.url, timeout=120) as http:
        cube = http.get("/v1/examples/1").content  # simulated once: the page's request answers from the cache
    page = rendered(f"{server.url}/viewer?example=1", tmp_path / "browser")
    # What the API answers for the same cube: the page must show exactly this.
    with httpx.Client(base_url=server.url, timeout=120) as http:
        answer = http.post("/v1/segment?outputs=objects,masks,views&encoding=zlib", content=cube,
                           headers=NPY).json()
        bad = b"this is not a .npy file"
        refusal = http.post("/v1/segment", content=bad, headers=NPY)
    bad_url = "data:application/octet-stream;base64," + base64.b64encode(bad).decode()
    bad_page = rendered(f"{server.url}/viewer?cube={quote(bad_url, safe='')}", tmp_path / "browser")
    missing_page = rendered(f"{server.url}/viewer?example=9", tmp_path / "browser")

    assert page.attrs["body"]["data-state"] == "done", page.text.get("message")
    assert answer["objects"], "the shipped model found no object in example 1: the test would check nothing"
    for view, mask in (("ra-view", "ra_mask"), ("rd-view", "rd_mask")):
        canvas = page.attrs[view]
        assert canvas["data-drawn"] == "true"
        assert int(canvas["data-mask-cells"]) == np.count_nonzero(decode_array(answer[mask])) > 0
        assert int(canvas["data-markers"]) == len(answer["objects"])
    assert [row["data-class"] for row in page.rows] == [o["class_name"] for o in answer["objects"]]
    assert page.attrs["macs-total"]["title"] == f"{answer['compute']['macs']['total']} MACs"
    assert "MACs" in page.text["macs-total"] and "MACs" in page.text["compute"]
    assert page.text["roi-voxels"].replace(",", "") == str(answer["compute"]["roi_voxels"])
    assert "anonymous" in page.text["usage"]

    assert refusal.status_code == 400
    assert (bad_page.attrs["body"]["data-state"], bad_page.attrs["body"]["data-status"]) == ("error", "400")
    assert refusal.json()["detail"] in bad_page.text["message"]
    assert bad_page.attrs["ra-view"]["data-drawn"] == "false"
    assert (missing_page.attrs["body"]["data-state"], missing_page.attrs["body"]["data-status"]) == ("error", "404")
    assert "no example 9" in missing_page.text["message"]


def test_viewer_plays_an_example_as_a_stream_with_tracks_and_velocity_arrows(server, tmp_path):
    page = rendered(f"{server.url}/viewer?stream=1", tmp_path / "browser")
    with httpx.Client(base_url=server.url, timeout=120) as http:  # the same frames as a stream of our own
        frames = http.get("/v1/examples").json()["examples"][0]["frames"]
        stream = http.post("/v1/streams").json()["id"]
        answers = [http.post(f"/v1/streams/{stream}/frames?seq={k}&outputs=objects", headers=NPY,
                             content=http.get(f"/v1/examples/1?frame={k}").content).json()
                   for k in range(frames)]
        left = http.get(f"/v1/streams/{stream}").json()["frames"]

    assert page.attrs["body"]["data-state"] == "done", page.text.get("message")
    last = answers[-1]
    assert last["objects"], "the shipped model found nothing in the example's last frame: nothing to check"
    canvas = page.attrs["ra-view"]
    assert int(canvas["data-frames"]) == frames == left
    assert int(canvas["data-arrows"]) == len(last["objects"])
    seen: dict[int, int] = {}
    for answer in answers:
        for obj in answer["objects"]:
            seen[obj["track_id"]] = seen.get(obj["track_id"], 0) + 1
    assert int(canvas["data-trails"]) == sum(1 for count in seen.values() if count > 1) > 0
    assert [row["data-track"] for row in page.rows] == [str(o["track_id"]) for o in last["objects"]]
    assert f"{len(last['stream']['tracks'])} track" in page.text["message"]
