"""The documentation site builds offline with ``mkdocs build --strict`` (every link between pages, every nav entry and
every anchor checked), its reference pages hold every command, route, setting and profile key the code has (they
are generated from it at build time by docs/hooks/reference.py), and the built pages fetch nothing from elsewhere.

Rendered in a real browser (Debian's ``chromium``, headless, as tests/service/test_viewer.py drives it) from a local
HTTP server: search answers a query, no entry of the command-line reference is empty, every picture loads."""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.browser import CHROMIUM, settled_html

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{done.stdout[-3000:]}{done.stderr[-6000:]}"
    return out


def _text(site: Path, page: str) -> str:
    html = (site / page / "index.html").read_text()
    return re.sub(r"<[^>]+>", "", html).replace("&quot;", '"').replace("&lt;", "<").replace("&gt;", ">")


@pytest.mark.slow
def test_the_cli_reference_has_every_command_and_option(site):
    """Every command, the jobs' own subcommands included (their options are read by the job's parser, not the
    top-level one), with every option in its own section: no entry is a bare usage line."""
    from pipelines.cli import JOBS, build_parser, job_parser_of

    html = (site / "reference" / "cli" / "index.html").read_text()
    sections = {}  # each command's heading -> the text of its section
    for chunk in html.split("<h2")[1:]:
        heading = re.search(r"<code>([^<]*)</code>", chunk)
        if heading:
            sections[heading.group(1)] = re.sub(r"<[^>]+>", "", chunk).replace("&lt;", "<").replace("&gt;", ">")

    def walk(parser: argparse.ArgumentParser, words: list[str]) -> None:
        if len(words) == 2 and words[1] in JOBS:
            parser = job_parser_of(words[1])
        command = " ".join(words)
        assert command in sections, f"{command} has no section in the CLI reference"
        assert f"usage: {command}" in sections[command], f"{command}: no usage line in its section"
        for action in parser._actions:
            if action.help == argparse.SUPPRESS:
                continue  # a renamed option, kept only to refuse its old name
            for flag in action.option_strings:
                assert flag in sections[command], f"{command} {flag} is not in its section of the CLI reference"
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    walk(child, [*words, name])

    walk(build_parser(), ["radarseg"])


@pytest.mark.slow
def test_the_http_reference_has_every_route_the_settings_and_profile_keys(site):
    from models.environment import Environment
    from radar.profiles.files import _SCHEMA
    from service.main import create_app
    from service.settings import Settings

    api = _text(site, "reference/http-api")
    openapi = create_app(Settings()).openapi()
    for path, methods in openapi["paths"].items():
        for method in methods:
            assert f"{method.upper()} {path}" in api, f"{method.upper()} {path} is not in the HTTP reference"
    # the schemas as tables a reader reads, not raw JSON schema
    assert '{"type"' not in api and '"$ref"' not in api
    for name, schema in openapi["components"]["schemas"].items():
        assert name in api, f"schema {name} is not in the HTTP reference"
        for field in schema.get("properties", {}):
            assert field in api, f"{name}.{field} is not in the HTTP reference"
    settings = _text(site, "reference/settings")
    for name in Settings.model_fields:
        assert f"RADARSEG_{name.upper()}" in settings, f"RADARSEG_{name.upper()} is not in the settings reference"
    for variable in Environment.variables().values():
        assert variable in settings, f"{variable} (models.environment) is not in the settings reference"
    profile = _text(site, "reference/radar-profile")
    for table, keys in _SCHEMA.items():
        for key in keys:
            assert key in profile and (not table or f"[{table}]" in profile), f"[{table}] {key} is not documented"


@pytest.mark.slow
def test_the_built_site_fetches_nothing_from_elsewhere(site):
    """Offline: no web font, script, stylesheet or picture from another host (links to other sites are fine)."""
    fetched = re.compile(r"""<(?:script|link|img|source)\b[^>]*\b(?:src|href)=["'](?:https?:)?//""")
    for page in site.rglob("*.html"):
        html = page.read_text()
        assert not fetched.search(html), f"{page.relative_to(site)} loads {fetched.search(html).group(0)}"
        assert "fonts.googleapis" not in html and "fonts.gstatic" not in html, page


def test_every_page_is_in_the_nav_or_generated():
    """A page written under docs/ and left out of mkdocs.yml's nav is a page nobody finds: listed here until it is
    added."""
    import yaml

    def paths(entries: list) -> set[str]:
        found = set()
        for entry in entries:
            for value in (entry.values() if isinstance(entry, dict) else [entry]):
                found |= paths(value) if isinstance(value, list) else {value}
        return found

    nav = paths(yaml.safe_load((REPO / "mkdocs.yml").read_text().replace("!!python", "#"))["nav"])
    pages = {str(p.relative_to(REPO / "docs")) for p in (REPO / "docs").rglob("*.md") if "hooks" not in p.parts}
    assert not pages - nav, f"pages missing from the nav: {sorted(pages - nav)}"


# -- the site in a browser ------------------------------------------------------------------------------------------
# .ci/run installs chromium and sets RADARSEG_REQUIRE_BROWSER=1: there a missing browser fails these tests.
needs_browser = pytest.mark.skipif(CHROMIUM is None and os.environ.get("RADARSEG_REQUIRE_BROWSER") != "1",
                                   reason="chromium is not installed (.ci/run installs it)")

# Added to every page the test serves: once the page has loaded, each picture's state goes into the DOM that
# chromium dumps (a picture that did not load has naturalWidth 0). With a query in the URL it also waits for search's
# results: the search worker builds its index in real time, which virtual time does not wait for, but it does wait
# for a pending request, so the probe asks the server for pauses of PAUSE_S until the results are drawn (30 s at most).
PAUSE = "/__pause"  # the address PROBE fetches
PAUSE_S = 0.2
PROBE = """<script>
addEventListener("load", async () => {
  document.body.dataset.images = JSON.stringify(
    [...document.images].map(image => [image.getAttribute("src"), image.complete && image.naturalWidth > 0]));
  if (!new URL(location.href).searchParams.has("q")) return;
  for (let i = 0; i < 150 && !document.querySelector(".md-search-result__item"); i++) await fetch("/__pause");
  document.body.dataset.searched = "yes";
});
</script>"""


@pytest.fixture(scope="module")
def served(site, tmp_path_factory) -> Iterator[str]:
    """The built site, each page with :data:`PROBE`, on a loopback HTTP server (search's web worker and its index
    need http://, not file://); yields its base URL."""
    root = tmp_path_factory.mktemp("served") / "site"
    shutil.copytree(site, root)
    for page in root.rglob("*.html"):
        page.write_text(page.read_text().replace("</body>", PROBE + "</body>"))

    class Site(http.server.SimpleHTTPRequestHandler):
        def do_GET(self) -> None:
            if self.path == PAUSE:
                time.sleep(PAUSE_S)
                self.send_response(204)
                self.end_headers()
            else:
                super().do_GET()

        def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (the base class's name)
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Site, directory=str(root)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        thread.join()


# What PROBE writes once it has looked: the pictures on load, and with a query in the URL, the search results.
SETTLED = ("document.body.dataset.images !== undefined"
           " && (!new URL(location.href).searchParams.has('q') || document.body.dataset.searched === 'yes')")


def rendered(url: str, profile: Path) -> str:
    """The page's DOM once :data:`PROBE` wrote its findings, waited on in real time (tests/browser.py)."""
    return settled_html(url, profile, SETTLED)


def _plain(html: str) -> str:
    return re.sub(r"<[^>]+>", "", html).replace("&quot;", '"').replace("&lt;", "<").replace("&gt;", ">")


@pytest.mark.slow
@needs_browser
def test_search_answers_a_query(served, tmp_path):
    """Material's search (a web worker over search/search_index.json) with the query in the URL, as a shared search
    link gives it: the results list the pages that hold the words."""
    html = rendered(f"{served}/?q=region+growing", tmp_path / "browser")
    assert 'data-searched="yes"' in html, "the page never finished loading"
    results = re.search(r'<ol class="md-search-result__list"[^>]*>(.*?)</ol>', html, re.S)
    assert results, "no search results list on the page"
    targets = re.findall(r'<a href="([^"]+)"', results.group(1))
    assert targets, f"search for 'region growing' found nothing: {_plain(html)[-500:]}"
    assert any("design/" in target for target in targets), f"design.md (section 6) is not among {targets[:10]}"
    meta = re.search(r'class="md-search-result__meta"[^>]*>([^<]*)<', html)
    assert meta and re.search(r"\d+ matching documents?", meta.group(1)), meta and meta.group(1)


@pytest.mark.slow
@needs_browser
def test_no_entry_of_the_cli_reference_is_empty(served, tmp_path):
    """Each command's section, as the browser shows it, holds its usage and at least one option or argument line
    (the job commands were once a bare usage line)."""
    html = rendered(f"{served}/reference/cli/", tmp_path / "browser")
    sections = html.split("<h2")[1:]
    assert len(sections) > 20, f"the CLI reference shows {len(sections)} commands"
    for chunk in sections:
        command = _plain("<h2" + chunk).strip().split("\n", 1)[0].rstrip("¶").strip()
        block = re.search(r"<pre.*?</pre>", chunk, re.S)
        assert block and "usage: radarseg" in _plain(block.group(0)), f"{command}: no usage line"
        described = re.findall(r"^ {2}(?:-{1,2}\w|\w|\{)", _plain(block.group(0)), re.M)
        assert described, f"{command}: its entry shows no option and no argument"


@pytest.mark.slow
@needs_browser
def test_every_picture_on_the_pages_loads(site, served, tmp_path):
    pages = sorted(p.relative_to(site).parent.as_posix() for p in site.rglob("index.html") if "<img" in p.read_text())
    assert {"results", "design"} <= set(pages), f"pages with pictures: {pages}"
    for page in pages:
        html = rendered(f"{served}/{page}/", tmp_path / "browser")
        state = re.search(r'<body[^>]*\bdata-images="([^"]*)"', html)
        assert state, f"{page}: the page never finished loading"
        images = json.loads(state.group(1).replace("&quot;", '"'))
        assert images, f"{page}: the browser saw no picture"
        broken = [src for src, loaded in images if not loaded]
        assert not broken, f"{page}: pictures that did not load: {broken}"
