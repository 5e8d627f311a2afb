"""Debian's chromium, headless, as the browser tests drive it: a page's DOM after its scripts ran."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

CHROMIUM = shutil.which("chromium")


def dump_dom(url: str, profile: Path, *, budget_ms: int) -> str:
    """The DOM of ``url`` after ``budget_ms`` of virtual time (chromium's --dump-dom), in a fresh profile folder."""
    assert CHROMIUM is not None, "chromium is not installed: apt-get install -y chromium (.ci/run does)"
    browser = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
         "--disable-extensions", "--disable-background-networking", f"--user-data-dir={profile}",
         "--window-size=1400,1050", f"--virtual-time-budget={budget_ms}", "--dump-dom", url],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        html, _ = browser.communicate(timeout=180)
    finally:
        if browser.poll() is None:
            browser.kill()  # by pid
            browser.wait()
    assert browser.returncode == 0, f"chromium exited with {browser.returncode} on {url}"
    return html
