"""The Open Inference Protocol's infer against POST /v1/segment on the same cubes, at concurrency 1: a real
``python -m service`` (uvicorn) on loopback with the shipped ``small`` pair and its default SQLite ledger; one
client, requests alternating between the routes frame by frame (side by side, so the machine's load hits both alike).

``/v1/segment`` gets the .npy complex cube and answers its default outputs (objects, RLE masks); the V2 route gets the
same cube through ``tritonclient.http`` as FP32 [R, A, D, 2] with the binary tensor data extension and answers the
same content (objects, RA/RD masks, compute) as binary tensors. Goal: V2's median client time within 1.05x of
/v1/segment's. A few requests with JSON tensors (the cube's log power as a JSON list) show what the binary extension
saves. Figures go to benchmarks/results/open_inference.json with the CPU, its flags and the load average; nothing is
asserted.

    .venv/bin/python -m benchmarks.open_inference [--frames 40] [--json-requests 3]
"""

from __future__ import annotations

import io
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from benchmarks.harness import int_options_main
from benchmarks.recording_export import machine
from pipelines.demo.serve_process import serving
from radar.simulate import simulate_sequence
from radar.transforms import log_power
from service.server.http_server import server_command

RESULTS = Path(__file__).resolve().parent / "results" / "open_inference.json"
MODEL = "small"  # the first model the default settings serve (the shipped pair)
V2_OUTPUTS = ("ra_mask", "rd_mask", "objects", "compute")


def _npy(cube: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, cube)
    return buffer.getvalue()


def _v2_request(cube: np.ndarray, *, binary: bool, kind: str = "complex") -> tuple[list, list]:
    """The inputs and outputs of a V2 request of ``cube``, prepared before the clock starts (as the .npy body of
    /v1/segment is)."""
    import tritonclient.http as triton

    tensor = np.stack([cube.real, cube.imag], -1).astype(np.float32) if kind == "complex" else cube
    infer_input = triton.InferInput(kind, list(tensor.shape), "FP32")
    infer_input.set_data_from_numpy(tensor, binary_data=binary)
    return [infer_input], [triton.InferRequestedOutput(name, binary_data=binary) for name in V2_OUTPUTS]


def _time_routes(url: str, http: httpx.Client, client, cubes: list[np.ndarray]) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {"segment": [], "v2_binary": []}
    for k, cube in enumerate(cubes):
        body, (inputs, outputs) = _npy(cube), _v2_request(cube, binary=True)
        for route in (("segment", "v2_binary") if k % 2 == 0 else ("v2_binary", "segment")):
            start = time.perf_counter()
            if route == "segment":
                response = http.post(f"{url}/v1/segment", content=body, headers={"content-type": "application/x-npy"})
                if response.status_code != 200:
                    raise RuntimeError(f"/v1/segment: {response.status_code} {response.text[:300]}")
            else:
                client.infer(MODEL, inputs, outputs=outputs)
            if k:  # the first frame of each route warms up
                times[route].append(time.perf_counter() - start)
    return times


def run(frames: int, json_requests: int, seed: int) -> dict:
    import tritonclient.http as triton

    data_dir = Path(tempfile.mkdtemp(prefix="radarseg-v2-bench-"))
    cubes = [frame.cube for frame in simulate_sequence("small", frames + 1, seed=seed)]
    with serving(data_dir, timeout_s=400, command=server_command) as (url, port), \
            httpx.Client(timeout=120) as http, \
            triton.InferenceServerClient(f"127.0.0.1:{port}", network_timeout=300) as client:
        before = machine()
        times = _time_routes(url, http, client, cubes)
        json_times = []
        for cube in cubes[:json_requests]:
            inputs, outputs = _v2_request(log_power(cube).astype(np.float32), binary=False, kind="log_power")
            start = time.perf_counter()
            client.infer(MODEL, inputs, outputs=outputs)
            json_times.append(time.perf_counter() - start)
    median = {route: float(np.median(v)) for route, v in times.items()}
    return {
        "frames_per_route": len(times["segment"]), "seed": seed, "preset": "small", "concurrency": 1,
        "median_s": median, "p90_s": {route: float(np.percentile(v, 90)) for route, v in times.items()},
        "v2_over_segment_median": median["v2_binary"] / median["segment"], "goal_ratio": 1.05,
        "v2_json_log_power_median_s": float(np.median(json_times)) if json_times else None,
        "machine_before": before, "machine_after": machine(),
    }


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, frames=40, json_requests=3, seed=25411)


if __name__ == "__main__":
    sys.exit(main())
