"""MkDocs hook: guides that are written beside the site's own pages join the nav once their file exists.

``mkdocs.yml`` lists the pages the site always has; a page of :data:`GUIDES` not listed there is added to the
"Guides" section when ``docs/<path>`` exists and left out while it does not, so ``mkdocs build --strict`` (which
refuses a nav entry without its file) passes at every step. A page listed in ``mkdocs.yml`` is never added twice.
"""

from __future__ import annotations

from pathlib import Path

GUIDES = (
    ("Deploy and scale out", "guides/deploy.md"),
    ("Recordings", "guides/recordings.md"),
    ("TI radars", "guides/ti-radar.md"),
    ("Live capture", "guides/live-capture.md"),
    ("Indoor scenes", "guides/indoor-scenes.md"),
    ("Service limits", "guides/service-limits.md"),
    ("Open inference", "guides/open-inference.md"),
)


def _paths(nav: list) -> set[str]:  # noqa: ANN001
    found = set()
    for entry in nav:
        for value in (entry.values() if isinstance(entry, dict) else [entry]):
            found |= _paths(value) if isinstance(value, list) else {value}
    return found


def on_config(config):  # noqa: ANN001, ANN201
    nav = config["nav"]
    listed = _paths(nav)
    guides = next(entry["Guides"] for entry in nav if isinstance(entry, dict) and "Guides" in entry)
    for title, path in GUIDES:
        if path not in listed and (Path(config["docs_dir"]) / path).is_file():
            guides.append({title: path})
    return config
