"""The browser tests' driver (tests/browser.py) reads a page only once the page says it has settled, however long
its requests take: a page whose one request is answered after 3 s is read with that answer, and a page that never
settles fails the wait with what it waited for."""

from __future__ import annotations

import functools
import http.server
import os
import threading
import time
from collections.abc import Iterator

import pytest

from tests.browser import CHROMIUM, Dom, settled_html

REQUIRED = os.environ.get("RADARSEG_REQUIRE_BROWSER") == "1"
pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None and not REQUIRED,
                                                   reason="chromium is not installed (.ci/run installs it)")]
SLOW_S = 3.0
PAGE = b"""<!doctype html><html><body data-state="loading"><p id="answer">none yet</p><script>
fetch("/slow").then(r => r.text()).then(text => {
  document.getElementById("answer").textContent = text;
  document.body.dataset.state = "done";
});
</script></body></html>"""


class Site(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        if self.path == "/slow":
            time.sleep(SLOW_S)
            body, kind = b"the slow answer", "text/plain"
        else:
            body, kind = PAGE, "text/html"
        self.send_response(200)
        self.send_header("content-type", kind)
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (the base class's name)
        pass


@pytest.fixture
def site() -> Iterator[str]:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Site))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        thread.join()


def test_a_page_is_read_once_its_slow_answer_came(site, tmp_path):
    started = time.monotonic()
    page = Dom(settled_html(f"{site}/", tmp_path / "browser", "document.body.dataset.state === 'done'"))
    assert page.attrs["body"]["data-state"] == "done"
    assert page.text["answer"] == "the slow answer"
    assert time.monotonic() - started >= SLOW_S


def test_a_page_that_never_settles_fails_the_wait_and_says_on_what(site, tmp_path):
    with pytest.raises(AssertionError, match=r"within 5 s"):
        settled_html(f"{site}/", tmp_path / "browser", "document.body.dataset.state === 'never'", timeout_s=5)
