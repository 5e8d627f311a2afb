"""Debian's chromium, headless, as the browser tests drive it: one page over the DevTools protocol, waited on in
real time for a condition the page itself states (``document.body.dataset``), never on a budget of virtual time.

A virtual-time budget (``--virtual-time-budget`` with ``--dump-dom``) runs out in milliseconds of real time when the
page only waits on the network: on a loaded machine the service's answer came after the DOM was dumped, and the page
was read still ``loading``. Here a page is read only once it says it has settled, or the wait fails with what it
waited for."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from html.parser import HTMLParser
from pathlib import Path

import httpx

CHROMIUM = shutil.which("chromium")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
         "--disable-extensions", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--window-size=1400,1050")
SETTLE_S = 300.0  # the longest a page may take to settle: a service under load answers slowly, never not at all


class Browser:
    """A headless chromium and its page, driven over the DevTools protocol (one websocket, commands in turn)."""

    def __init__(self, profile_dir: Path) -> None:
        assert CHROMIUM is not None, "chromium is not installed: apt-get install -y chromium (.ci/run does)"
        profile_dir.mkdir(parents=True, exist_ok=True)
        port_file = profile_dir / "DevToolsActivePort"
        port_file.unlink(missing_ok=True)  # an earlier browser's, in a profile used again
        self.proc = subprocess.Popen(
            [CHROMIUM, *FLAGS, f"--user-data-dir={profile_dir}", "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self._wait(lambda: port_file.is_file() and port_file.read_text().count("\n") >= 1, 120, "chromium's port")
        port = int(port_file.read_text().split()[0])
        pages = [t for t in httpx.get(f"http://127.0.0.1:{port}/json/list").json() if t["type"] == "page"]
        self.address = pages[0]["webSocketDebuggerUrl"]
        self.socket = None  # connected by browser()
        self.ids = itertools.count(1)

    def _wait(self, ready: Callable[[], object], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not ready():
            assert self.proc.poll() is None, f"chromium exited with {self.proc.returncode}"
            assert time.monotonic() < deadline, f"no {what} within {timeout_s} s"
            time.sleep(0.2)

    def send(self, method: str, **params) -> dict:
        number = next(self.ids)
        self.socket.send(json.dumps({"id": number, "method": method, "params": params}))
        while True:  # events in between are not needed
            message = json.loads(self.socket.recv(timeout=SETTLE_S))
            if message.get("id") == number:
                assert "error" not in message, message
                return message["result"]

    def evaluate(self, expression: str):
        return self.send("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def until(self, expression: str, timeout_s: float = SETTLE_S) -> None:
        self._wait(lambda: self.evaluate(expression), timeout_s, expression)

    def open(self, url: str, settled: str, timeout_s: float = SETTLE_S) -> str:
        """The page at ``url`` once the JavaScript expression ``settled`` is true: its DOM as HTML."""
        self.evaluate("window.radarsegLeft = true")  # gone once the new page is there
        self.send("Page.navigate", url=url)
        self.until(f"!window.radarsegLeft && document.readyState === 'complete' && ({settled})", timeout_s)
        return self.html()

    def html(self) -> str:
        return self.evaluate("document.documentElement.outerHTML")

    def close(self) -> None:
        self.proc.kill()  # by pid
        self.proc.wait()


@contextmanager
def browser(profile_dir: Path) -> Iterator[Browser]:
    from websockets.sync.client import connect

    started = Browser(profile_dir)
    try:
        with connect(started.address, max_size=None, open_timeout=60) as started.socket:
            yield started
    finally:
        started.close()


def settled_html(url: str, profile_dir: Path, settled: str, timeout_s: float = SETTLE_S) -> str:
    """One page in a fresh browser: its DOM once ``settled`` is true (see :meth:`Browser.open`)."""
    with browser(profile_dir) as chromium:
        return chromium.open(url, settled, timeout_s)


class Dom(HTMLParser):
    """A rendered page: attributes and text of every element with an id, and the table rows with ``data-index``."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.attrs: dict[str, dict[str, str]] = {}
        self.text: dict[str, str] = {}
        self.rows: list[dict[str, str]] = []
        self._open: list[tuple[str, str | None]] = []
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = {name: value or "" for name, value in attrs}
        if tag == "body":
            self.attrs["body"] = values
        if "id" in values:
            self.attrs[values["id"]] = values
            self.text.setdefault(values["id"], "")
        if tag == "tr" and "data-index" in values:
            self.rows.append(values)
        if tag not in ("br", "img", "input", "link", "meta"):
            self._open.append((tag, values.get("id")))

    def handle_endtag(self, tag: str) -> None:
        while self._open:
            if self._open.pop()[0] == tag:
                break

    def handle_data(self, data: str) -> None:
        for _, element_id in self._open:
            if element_id is not None:
                self.text[element_id] += data
