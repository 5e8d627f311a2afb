"""Container health checks of the radarseg image (standard library only; exit 0 = healthy).

::

    python deploy/healthcheck.py api [--url http://127.0.0.1:8000]   # GET /healthz answers 200
    python deploy/healthcheck.py raylet                             # a Ray raylet runs in this container

The Ray head uses Ray's own ``ray health-check`` (GCS reachable); a worker node has no port of its own
to ask, so its check is that its raylet process is alive.
"""

from __future__ import annotations

import argparse
import os
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path


def api_healthy(url: str, timeout_s: float = 4.0) -> bool:
    """True when ``GET {url}/healthz`` answers 200."""
    try:
        with urllib.request.urlopen(f"{url.rstrip('/')}/healthz", timeout=timeout_s) as resp:
            return resp.status == 200
    except (urllib.error.URLError, OSError):
        return False


def process_stats(proc: Path = Path("/proc")) -> Iterator[tuple[int, str, list[str]]]:
    """Each process of ``proc`` as (pid, executable name, the fields of ``/proc/PID/stat`` after the name: state
    first, then the parent pid and the process group); one that ends while read is passed over."""
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        yield int(entry.name), stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()


def raylet_running(proc: Path = Path("/proc")) -> bool:
    """True when a process whose executable name is ``raylet`` runs (and is not a zombie)."""
    return any(name == "raylet" and fields[0] != "Z" for _, name, fields in process_stats(proc))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("role", choices=["api", "raylet"])
    parser.add_argument("--url", default=f"http://127.0.0.1:{os.environ.get('RADARSEG_PORT', '8000')}",
                        help="API base URL (default: loopback on RADARSEG_PORT or 8000)")
    args = parser.parse_args(argv)
    healthy = api_healthy(args.url) if args.role == "api" else raylet_running()
    if not healthy:
        print(f"{args.role}: unhealthy", file=sys.stderr)
    return 0 if healthy else 1


if __name__ == "__main__":
    sys.exit(main())
