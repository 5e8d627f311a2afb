"""A stream's frame against /v1/segment on the same cubes: a real ``python -m service`` (uvicorn) on loopback
with the shipped ``small`` pair and its default SQLite ledger; one client, requests alternating between the two
routes frame by frame (side by side, so the machine's load hits both alike).

Written to benchmarks/results/streams.json: the median and p90 client time of each route, their ratio (goal: a stream
frame's median within 1.1x of /v1/segment's), the server's own ``track`` stage (the tracker) and the load average.

    .venv/bin/python -m benchmarks.streams [--sequences 3] [--frames 20]
"""

from __future__ import annotations

import io
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.harness import int_options_main
from pipelines.demo.serve_process import serving
from radar.simulate import simulate_sequence
from service.server.http_server import server_command

RESULTS = Path(__file__).resolve().parent / "results" / "streams.json"
NPY = {"content-type": "application/x-npy"}


def _npy(cube: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, cube)
    return buffer.getvalue()


def _cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


def _timed(http: httpx.Client, url: str, body: bytes) -> tuple[float, httpx.Response]:
    start = time.perf_counter()
    response = http.post(url, content=body, headers=NPY)
    elapsed = time.perf_counter() - start
    if response.status_code != 200:
        raise RuntimeError(f"{url}: {response.status_code} {response.text[:300]}")
    return elapsed, response


def run(sequences: int, frames: int, seed: int) -> dict:
    data_dir = Path(tempfile.mkdtemp(prefix="radarseg-streams-bench-"))
    times: dict[str, list[float]] = {"segment": [], "stream": []}
    with serving(data_dir, timeout_s=180, command=server_command) as (url, _), \
            httpx.Client(base_url=url, timeout=120) as http:
        for s in range(sequences):
            cubes = [_npy(f.cube) for f in simulate_sequence("small", frames, seed=seed + s)]
            stream = http.post("/v1/streams").json()["id"]
            for k, body in enumerate(cubes):
                order = ("segment", "stream") if k % 2 == 0 else ("stream", "segment")
                for route in order:
                    path = (f"/v1/streams/{stream}/frames?seq={k}" if route == "stream" else "/v1/segment")
                    elapsed, response = _timed(http, path, body)
                    if s or k:  # the very first frame of each route warms up
                        times[route].append(elapsed)
            http.delete(f"/v1/streams/{stream}")
        metrics = http.get("/metrics").text
    track = {}  # the server's own "track" stage: sum (s) and count of its histogram
    for line in metrics.splitlines():
        for kind in ("sum", "count"):
            if line.startswith(f"radarseg_stage_duration_seconds_{kind}") and 'stage="track"' in line:
                track[kind] = float(line.rsplit(" ", 1)[1])
    median = {route: float(np.median(v)) for route, v in times.items()}
    return {
        "frames_per_route": len(times["segment"]), "sequences": sequences, "seed": seed,
        "median_s": median, "p90_s": {route: float(np.percentile(v, 90)) for route, v in times.items()},
        "stream_over_segment_median": median["stream"] / median["segment"],
        "track_ms_mean": 1e3 * track["sum"] / track["count"] if track.get("count") else None,
        "load_average": os.getloadavg(), "cpu": _cpu(), "when": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, sequences=3, frames=20, seed=25401)


if __name__ == "__main__":
    sys.exit(main())
