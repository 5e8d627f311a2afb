"""The viewer opens what a TI radar gives: OpenRadar's recorded frame as an ADC frame (.npy, int16 I/Q, "ti" layout)
and a DCA1000 capture (.bin, written by the capture writer) of several frames, read with the served model's radar
profile, a frame picked with the frame index control; undecoded words answered with the service's one line.

A real browser (Debian's ``chromium``, headless) drives the page over the DevTools protocol: each file is put into
the page's file input as a user picks it, against a real ``radarseg serve`` on loopback serving an untrained tiny
model of the recorded radar; what the page draws is compared with what the API answers for the same bytes. The
browser and the server are stopped by pid."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest

from radar.ti.capture_writer import write_dca1000
from radar.ti.dca1000 import CaptureFormat
from service.encoding import decode_array
from tests.service.conftest import NPY, npy_bytes
from tests.service.openradar_model import (
    as_complex,
    openradar_profile,
    save_openradar_checkpoints,
    ti_frame_iq,
    undecoded_words,
)
from tests.service.test_viewer import Dom

# .ci/run installs chromium and sets RADARSEG_REQUIRE_BROWSER=1: there a missing browser fails the test.
CHROMIUM = shutil.which("chromium")
REQUIRED = os.environ.get("RADARSEG_REQUIRE_BROWSER") == "1"
OUTPUTS = "outputs=objects,masks,views&encoding=zlib"
SETTLED = "['done', 'error'].includes(document.body.dataset.state)"

pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None and not REQUIRED,
                                                   reason="chromium is not installed (.ci/run installs it)")]


class Browser:
    """A headless chromium and its page, driven over the DevTools protocol (one websocket, commands in turn)."""

    def __init__(self, profile_dir: Path) -> None:
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
             "--disable-extensions", "--disable-background-networking", f"--user-data-dir={profile_dir}",
             "--window-size=1400,1050", "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = profile_dir / "DevToolsActivePort"
        self._wait(lambda: port_file.is_file() and port_file.read_text().count("\n") >= 1, 60, "chromium's port")
        port = int(port_file.read_text().split()[0])
        pages = [t for t in httpx.get(f"http://127.0.0.1:{port}/json/list").json() if t["type"] == "page"]
        self.address = pages[0]["webSocketDebuggerUrl"]
        self.socket = None  # connected by browser()
        self.ids = itertools.count(1)

    def _wait(self, ready, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not ready():
            assert self.proc.poll() is None, f"chromium exited with {self.proc.returncode}"
            assert time.monotonic() < deadline, f"no {what} within {timeout_s} s"
            time.sleep(0.2)

    def send(self, method: str, **params) -> dict:
        number = next(self.ids)
        self.socket.send(json.dumps({"id": number, "method": method, "params": params}))
        while True:  # events in between are not needed
            message = json.loads(self.socket.recv(timeout=120))
            if message.get("id") == number:
                assert "error" not in message, message
                return message["result"]

    def evaluate(self, expression: str):
        return self.send("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def until(self, expression: str, timeout_s: float = 180) -> None:
        self._wait(lambda: self.evaluate(expression), timeout_s, expression)

    def open(self, url: str) -> None:
        self.send("Page.navigate", url=url)
        self.until("document.readyState === 'complete' && document.body.dataset.state === 'idle'")

    def pick(self, path: Path) -> Dom:
        """The file picked in "Open .npy / .bin", as a user does; the page once it has the service's answer."""
        self.evaluate("document.body.dataset.state = 'idle'")
        root = self.send("DOM.getDocument")["root"]["nodeId"]
        node = self.send("DOM.querySelector", nodeId=root, selector="#file")["nodeId"]
        self.send("DOM.setFileInputFiles", nodeId=node, files=[str(path)])
        self.until(SETTLED)
        return self.dom()

    def choose_frame(self, frame: int) -> Dom:
        self.evaluate(f"document.body.dataset.state = 'idle'; const box = document.getElementById('frame'); "
                      f"box.value = '{frame}'; box.dispatchEvent(new Event('change'));")
        self.until(SETTLED)
        return self.dom()

    def dom(self) -> Dom:
        return Dom(self.evaluate("document.documentElement.outerHTML"))

    def close(self) -> None:
        self.proc.kill()  # by pid
        self.proc.wait()


@contextmanager
def browser(profile_dir: Path) -> Iterator[Browser]:
    from websockets.sync.client import connect

    started = Browser(profile_dir)
    try:
        with connect(started.address, max_size=None) as started.socket:
            yield started
    finally:
        started.close()


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
        chromium.open(f"{server.url}/viewer")
        adc_page = chromium.pick(radar_files["adc"])
        capture_first = chromium.pick(radar_files["capture"])
        capture_last = chromium.choose_frame(2)
        cut_page = chromium.pick(radar_files["cut"])
        words_page = chromium.pick(radar_files["words"])
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
