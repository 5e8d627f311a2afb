"""The documentation site builds offline with ``mkdocs build --strict`` (every link between pages, every nav entry and
every anchor checked), its reference pages hold every command, route, setting and profile key the code has (they
are generated from it at build time by docs/hooks/reference.py), and the built pages fetch nothing from elsewhere."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

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
    for path, methods in create_app(Settings()).openapi()["paths"].items():
        for method in methods:
            assert f"{method.upper()} {path}" in api, f"{method.upper()} {path} is not in the HTTP reference"
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
