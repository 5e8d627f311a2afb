"""The HTTP service under load: a real ``radarseg serve`` (uvicorn) on loopback, a bounded request loop
at concurrency 1, 2 and 4 for ``small`` and ``carrada`` cubes; latency p50/p95, throughput, errors, and
where a request's time goes: receiving and decoding the body (the server's ``decode`` stage runs while the
body streams in, so it includes the upload), model stages, response encoding, and the rest (HTTP parsing
of the headers, the response transfer, queueing behind the model's one replica at concurrency > 1).
Prints a table and writes benchmarks/results/service.json.

    .venv/bin/python benchmarks/service.py [--requests-small 8 --requests-carrada 4] [--quick]

Models: the shipped ``small`` checkpoints when checkpoints/ holds them, else a real-size untrained
``centre_detector`` + ``minkunet`` for ``small``; ``carrada`` always uses real-size untrained models (no
trained carrada checkpoint exists). Untrained models run with score threshold 0 and 4 objects, so the
cost per request resembles a scene with four objects. Target (issue 7): overhead (everything but the
model stages) at most 10% of the p50 latency on carrada cubes; no errors under load.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

from pipelines.serve_process import free_port, serve_command, stop_process, wait_ready

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "service.json"
STAGES = ("transform", "detect", "grow", "segment", "project")
CLASSES = ("background", "pedestrian", "cyclist", "car")
SHIPPED = ("checkpoints/detector.pt", "checkpoints/segmenter.pt")


def _untrained(preset: str, out: Path) -> dict:
    import torch

    from models.checkpoint import Checkpoint, save_checkpoint
    from models.registry import create_model

    torch.manual_seed(0)
    det, seg = create_model("centre_detector", preset=preset), create_model("minkunet", preset=preset)
    return {"name": preset, "score_threshold": 0.0, "max_objects": 4,
            "detector": str(save_checkpoint(Checkpoint("centre_detector", {"preset": preset}, det.state_dict(), preset,
                                                       CLASSES, {"mean": 60.0, "std": 8.0}), out / f"{preset}_det.pt")),
            "segmenter": str(save_checkpoint(Checkpoint("minkunet", {"preset": preset}, seg.state_dict(), preset,
                                                        CLASSES), out / f"{preset}_seg.pt"))}


def _models(out: Path) -> tuple[list[dict], dict[str, str]]:
    if all((REPO / p).is_file() for p in SHIPPED):
        small = {"name": "small", "detector": SHIPPED[0], "segmenter": SHIPPED[1]}
        kinds = {"small": "shipped checkpoints"}
    else:
        small = _untrained("small", out)
        kinds = {"small": "real-size untrained centre_detector + minkunet (no shipped checkpoint yet)"}
    kinds["carrada"] = "real-size untrained centre_detector + minkunet (no trained carrada checkpoint)"
    return [small, _untrained("carrada", out)], kinds


def _start(models: list[dict], data_dir: Path, log: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = {**os.environ, "RADARSEG_MODELS": json.dumps(models), "RADARSEG_DATA_DIR": str(data_dir),
           "RADARSEG_MAX_QUEUE": "8"}
    proc = subprocess.Popen(serve_command(port), cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_ready(url, proc, log, timeout_s=300)
    except RuntimeError:
        stop_process(proc)
        raise
    return proc, url


def _server_timing(header: str) -> dict[str, float]:
    out = {}
    for part in header.split(","):
        name, _, dur = part.strip().partition(";dur=")
        out[name] = float(dur) / 1e3
    return out


def _one(http: httpx.Client, url: str, model: str, body: bytes) -> dict:
    start = time.perf_counter()
    r = http.post(f"{url}/v1/segment?model={model}", content=body, headers={"content-type": "application/x-npy"})
    latency = time.perf_counter() - start
    if r.status_code != 200:
        return {"status": r.status_code, "latency_s": latency}
    timing = _server_timing(r.headers["server-timing"])
    return {"status": 200, "latency_s": latency, "receive_decode_s": timing["decode"], "encode_s": timing["encode"],
            "model_s": sum(timing[s] for s in STAGES), "macs": int(r.headers["x-compute-macs"]),
            "response_bytes": len(r.content)}


def run_level(url: str, model: str, body: bytes, concurrency: int, n_requests: int) -> dict:
    """``n_requests`` posts from ``concurrency`` client threads; latency and time shares."""
    with httpx.Client(timeout=600, limits=httpx.Limits(max_connections=concurrency)) as http:
        _one(http, url, model, body)  # warm the connection
        start = time.perf_counter()
        with ThreadPoolExecutor(concurrency) as pool:
            rows = list(pool.map(lambda _: _one(http, url, model, body), range(n_requests)))
        wall = time.perf_counter() - start
    ok = [r for r in rows if r["status"] == 200]
    latency = np.array([r["latency_s"] for r in ok])
    mean = float(latency.mean()) if len(ok) else float("nan")
    shares = {}
    if ok:
        for part in ("receive_decode_s", "model_s", "encode_s"):
            shares[part.removesuffix("_s")] = float(np.mean([r[part] for r in ok])) / mean
        shares["http_transfer_and_queue"] = 1.0 - sum(shares.values())
    p50 = float(np.percentile(latency, 50)) if len(ok) else float("nan")
    model_p50 = float(np.median([r["model_s"] for r in ok])) if ok else float("nan")
    return {
        "concurrency": concurrency, "requests": n_requests, "errors": len(rows) - len(ok),
        "p50_s": p50, "p95_s": float(np.percentile(latency, 95)) if len(ok) else float("nan"),
        "throughput_rps": len(ok) / wall, "mean_latency_s": mean, "share_of_mean_latency": shares,
        "model_stages_p50_s": model_p50,
        "overhead_share_of_p50": (p50 - model_p50) / p50 if ok else float("nan"),
        "macs_per_request": ok[0]["macs"] if ok else None, "response_bytes": ok[0]["response_bytes"] if ok else None,
    }


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests-small", type=int, default=8, help="requests per concurrency level")
    parser.add_argument("--requests-carrada", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="2 requests per level (a smoke run)")
    args = parser.parse_args()
    from radar.simulate import simulate_sequence

    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0]}
    results: dict = {"machine": machine, "levels": {}}
    with tempfile.TemporaryDirectory(prefix="rsg-bench-") as tmp:
        tmp = Path(tmp)
        models, kinds = _models(tmp)
        results["models"] = kinds
        proc, url = _start(models, tmp / "data", tmp / "server.log")
        try:
            for preset, n in (("small", args.requests_small), ("carrada", args.requests_carrada)):
                cube = next(simulate_sequence(preset, 1, seed=3)).cube
                buf = io.BytesIO()
                np.save(buf, cube)
                body = buf.getvalue()
                levels = []
                for concurrency in (1, 2, 4):
                    count = 2 if args.quick else max(n, concurrency * 2)
                    level = run_level(url, preset, body, concurrency, count)
                    level["body_bytes"] = len(body)
                    levels.append(level)
                    shares = level["share_of_mean_latency"]
                    print(f"{preset:8s} c={concurrency}  p50 {level['p50_s'] * 1e3:8.1f} ms  p95 "
                          f"{level['p95_s'] * 1e3:8.1f} ms  {level['throughput_rps']:6.2f} req/s  errors "
                          f"{level['errors']}  receive+decode {shares.get('receive_decode', 0):.1%}  model "
                          f"{shares.get('model', 0):.1%}  encode {shares.get('encode', 0):.1%}  other "
                          f"{shares.get('http_transfer_and_queue', 0):.1%}  overhead/p50 "
                          f"{level['overhead_share_of_p50']:.1%}", flush=True)
                results["levels"][preset] = levels
        finally:
            stop_process(proc, grace_s=30)
    carrada_c1 = results["levels"]["carrada"][0]
    results["target"] = {"carrada_overhead_share_of_p50_at_c1": carrada_c1["overhead_share_of_p50"],
                         "limit": 0.10, "met": carrada_c1["overhead_share_of_p50"] <= 0.10,
                         "errors": sum(lv["errors"] for lv in sum(results["levels"].values(), []))}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(f"written to {RESULTS.relative_to(REPO)}")
    return results


if __name__ == "__main__":
    main()
