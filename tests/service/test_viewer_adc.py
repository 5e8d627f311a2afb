"""The viewer opens what a TI radar gives: OpenRadar's recorded frame as an ADC frame (.npy, int16 I/Q, "ti" layout)
and a DCA1000 capture (.bin, written by the capture writer) of several frames, read with the served model's radar
profile, a frame picked with the frame index control; undecoded words answered with the service's one line.

A real browser (Debian's ``chromium``, headless) drives the page over the DevTools protocol: each file is put into
the page's file input as a user picks it, against a real ``radarseg serve`` on loopback serving an untrained tiny
model of the recorded radar; what the page draws is compared with what the API answers for the same bytes. The
browser and the server are stopped by pid."""

from __future__ import annotations

import json
import os
from pathlib import Path

import httpx
import numpy as np
import pytest

from radar.ti.capture_writer import write_dca1000
from radar.ti.dca1000 import CaptureFormat
from service.encoding import decode_array
from tests.browser import CHROMIUM, Browser, Dom, browser
from tests.service.conftest import NPY, npy_bytes
from tests.service.openradar_model import (
    as_complex,
    openradar_profile,
    save_openradar_checkpoints,
    ti_frame_iq,
    undecoded_words,
)

# .ci/run installs chromium and sets RADARSEG_REQUIRE_BROWSER=1: there a missing browser fails the test.
REQUIRED = os.environ.get("RADARSEG_REQUIRE_BROWSER") == "1"
OUTPUTS = "outputs=objects,masks,views&encoding=zlib"
SETTLED = "['done', 'error'].includes(document.body.dataset.state)"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None and not REQUIRED,
                                                   reason="chromium is not installed (.ci/run installs it)")]


def pick(chromium: Browser, path: Path) -> Dom:
    """The file picked in "Open .npy / .bin", as a user does; the page once it has the service's answer."""
    chromium.evaluate("document.body.dataset.state = 'idle'")
    root = chromium.send("DOM.getDocument")["root"]["nodeId"]
    node = chromium.send("DOM.querySelector", nodeId=root, selector="#file")["nodeId"]
    chromium.send("DOM.setFileInputFiles", nodeId=node, files=[str(path)])
    chromium.until(SETTLED)
    return Dom(chromium.html())


def choose_frame(chromium: Browser, frame: int) -> Dom:
    chromium.evaluate(f"document.body.dataset.state = 'idle'; const box = document.getElementById('frame'); "
                      f"box.value = '{frame}'; box.dispatchEvent(new Event('change'));")
    chromium.until(SETTLED)
    return Dom(chromium.html())


def drawn_like(page: Dom, answer: dict) -> None:
    """The page shows exactly the API's answer: both views drawn with its masks and markers, its objects."""
    assert page.attrs["body"]["data-state"] == "done", page.text.get("message")
    for view, mask in (("ra-view", "ra_mask"), ("rd-view", "rd_mask")):
        canvas = page.attrs[view]
        assert canvas["data-drawn"] == "true"
        assert int(canvas["data-mask-cells"]) == np.count_nonzero(decode_array(answer[mask]))
        assert int(canvas["data-markers"]) == len(answer["objects"])
    assert [row["data-class"] for row in page.rows] == [o["class_name"] for o in answer["objects"]]
    assert page.attrs["macs-total"]["title"] == f"{answer['compute']['macs']['total']} MACs"


@pytest.fixture
def radar_files(tmp_path) -> dict[str, Path]:
    """The recorded frame as an ADC .npy, a 3-frame DCA1000 capture (the frame, its chirps rolled, its samples
    reversed: ranges mirrored), the same capture cut short, and the frame's undecoded words."""
    ti = as_complex(ti_frame_iq())
    files = {"adc": tmp_path / "doppler_example_1_ti.npy", "capture": tmp_path / "adc_data.bin",
             "cut": tmp_path / "cut_adc_data.bin", "words": tmp_path / "undecoded_words.npy"}
    np.save(files["adc"], ti_frame_iq())
    write_dca1000(files["capture"], [ti, np.roll(ti, 2, axis=0), ti[..., ::-1].copy()],
                  CaptureFormat.of_profile(openradar_profile()))
    files["cut"].write_bytes(files["capture"].read_bytes()[:-1000])
    np.save(files["words"], undecoded_words())
    return files


def test_viewer_opens_an_adc_frame_and_a_capture_and_shows_refusals(serve, tmp_path, radar_files):
    assert CHROMIUM is not None, "chromium is not installed: apt-get install -y chromium (.ci/run does)"
    det, seg = save_openradar_checkpoints(tmp_path)
    model = {"name": "openradar", "detector": str(det), "segmenter": str(seg), "score_threshold": 0.0,
             "max_objects": 2}
    env = {"RADARSEG_DATA_DIR": str(tmp_path / "data"), "RADARSEG_WARMUP": "false",
           "RADARSEG_MODELS": json.dumps([model])}
    with serve(env) as (server,), browser(tmp_path / "browser") as chromium:
        chromium.open(f"{server.url}/viewer", "document.body.dataset.state === 'idle'")
        adc_page = pick(chromium, radar_files["adc"])
        capture_first = pick(chromium, radar_files["capture"])
        capture_last = choose_frame(chromium, 2)
        cut_page = pick(chromium, radar_files["cut"])
        words_page = pick(chromium, radar_files["words"])
        with httpx.Client(base_url=server.url, timeout=180) as http:  # the API's answers for the same bytes
            adc = http.post(f"/v1/segment?input=adc&{OUTPUTS}", content=radar_files["adc"].read_bytes(), headers=NPY)
            capture = radar_files["capture"].read_bytes()
            frames = [http.post(f"/v1/segment?input=adc&format=dca1000&frame={k}&{OUTPUTS}", content=capture,
                                headers={"content-type": "application/octet-stream"}) for k in (0, 2)]
            cut = http.post("/v1/segment?input=adc&format=dca1000", content=radar_files["cut"].read_bytes(),
                            headers={"content-type": "application/octet-stream"})
            words = http.post("/v1/segment?input=adc", content=npy_bytes(undecoded_words()), headers=NPY)

    assert adc.status_code == 200 and adc.json()["objects"], adc.text
    drawn_like(adc_page, adc.json())
    assert adc_page.attrs["body"]["data-input"] == "adc" and "hidden" in adc_page.attrs["frame-control"]

    assert all(answer.status_code == 200 for answer in frames)
    drawn_like(capture_first, frames[0].json())
    assert capture_first.attrs["body"]["data-input"] == "dca1000"
    assert "hidden" not in capture_first.attrs["frame-control"]
    assert capture_first.attrs["frame"]["max"] == "2" and capture_first.text["frame-count"] == "of 3 (0 to 2)"
    assert "adc_data.bin, frame 0 (3 frames, from 0)" in capture_first.text["message"]
    drawn_like(capture_last, frames[1].json())
    assert "adc_data.bin, frame 2 (3 frames, from 0)" in capture_last.text["message"]
    assert frames[0].json()["rd_mask"] != frames[1].json()["rd_mask"], "frames 0 and 2 alike: nothing shown"

    for page, answer in ((cut_page, cut), (words_page, words)):
        assert answer.status_code == 422, answer.text
        assert (page.attrs["body"]["data-state"], page.attrs["body"]["data-status"]) == ("error", "422")
        assert answer.json()["detail"] in page.text["message"]
        assert "Traceback" not in page.text["message"]
    assert "partial last frame" in cut_page.text["message"]
    assert "((x + 32768) % 65536) - 32768" in words_page.text["message"]
    assert "sent as an ADC frame" in words_page.text["message"]
