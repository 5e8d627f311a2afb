"""The HTTP service under load: a real ``python -m service`` (uvicorn) on loopback.

Three parts, each written into benchmarks/results/service.json with the load average it ran under (a part not
run keeps its previous figures):

- ``levels``: a bounded request loop at concurrency 1, 2 and 4 for ``small`` and ``carrada`` cubes; latency
  p50/p95, throughput, errors, and where a request's time goes: receiving and decoding the body (the server's
  ``decode`` stage runs while the body streams in, so it includes the upload), model stages, response encoding,
  and the rest (HTTP parsing of the headers, the response transfer, queueing behind the model's one replica at
  concurrency > 1).
- ``stages``: the model stages of the same frames inside the service (``Server-Timing``, at
  concurrency 1) against a plain process (``EraseNet.segment`` on the main thread of this process, with the
  service's torch thread count), side by side, and the client's p50 against the plain process's end to end.
- ``slow_clients``: normal clients alone (the idle p95), then the same clients while 16 clients
  upload at 1 KB/s (each reconnects when cut off with 408): the share of normal requests answered 200 and their
  p95 against the idle p95. Goal: >= 95 % and <= 2x.
- ``startup``: a fresh ``python -m service`` with the default models: seconds from the start of
  the process to the first ``/healthz`` 200 and to ``/readyz`` 200, and the stages its log reports (importing
  the service, each model's load and warm-up). Goals: ``/healthz`` within 2 s; ready in <= 10 s on an idle machine.
- ``fairness``: two tenants; one holds 10 uploads that send nothing (reopening each when answered),
  first declaring 64 MiB + 64 KiB (the issue's attack), then declaring a valid cube's length; the other tenant's
  requests meanwhile: the share answered 200. Goal: >= 95 %.

    .venv/bin/python -m benchmarks.service [--parts levels,stages,slow_clients,startup,fairness] [--quick]

Models: the shipped ``small`` checkpoints when checkpoints/ holds them, else a real-size untrained
``centre_detector`` + ``minkunet`` for ``small``; ``carrada`` always uses real-size untrained models (no
trained carrada checkpoint exists). Untrained models run with score threshold 0 and 4 objects, so the
cost per request resembles a scene with four objects. Figures are printed and written, never asserted.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

# `python benchmarks/service.py` puts benchmarks/ first on sys.path, where this file would shadow the `service` package.
if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
    sys.path.pop(0)

import httpx  # noqa: E402
import numpy as np  # noqa: E402

from pipelines.demo.serve_process import free_port, stop_process, wait_ready  # noqa: E402
from service.server.http_server import server_command  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "service.json"
STEPS = ("transform", "detect", "grow", "segment", "project")
CLASSES = ("background", "pedestrian", "cyclist", "car")
SHIPPED = ("checkpoints/detector.pt", "checkpoints/segmenter.pt")
PAUSE_S = 0.25  # between the interleaved runs of the stages part


def _cpu_flags() -> list[str]:
    """The SIMD flags of this CPU that matter to torch and numpy (from /proc/cpuinfo; empty elsewhere)."""
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags"))
    except (OSError, StopIteration):
        return []
    return sorted(set(flags.split(":", 1)[1].split()) & {"avx", "avx2", "avx512f", "fma", "sse4_2", "amx_tile"})


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
    proc = subprocess.Popen(server_command(port), cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
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
            "model_s": sum(timing[s] for s in STEPS), "macs": int(r.headers["x-compute-macs"]),
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


def _npy(cube: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, cube)
    return buf.getvalue()


def run_levels(url: str, args: argparse.Namespace) -> dict:
    from radar.simulate import simulate_sequence

    out = {}
    for preset, n in (("small", args.requests_small), ("carrada", args.requests_carrada)):
        body = _npy(next(simulate_sequence(preset, 1, seed=3)).cube)
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
        out[preset] = levels
    carrada_c1 = out["carrada"][0]
    return {"levels": out, "target": {"carrada_overhead_share_of_p50_at_c1": carrada_c1["overhead_share_of_p50"],
                                      "limit": 0.10, "met": carrada_c1["overhead_share_of_p50"] <= 0.10,
                                      "errors": sum(lv["errors"] for lv in sum(out.values(), []))}}


def run_stages(url: str, model: dict, frames: int) -> dict:
    """The same ``small`` frames (one from each of ``frames`` simulated sequences, with objects) through the
    service at concurrency 1, and through ``EraseNet.segment`` in this process, on its main thread with the
    service's torch thread count (a plain process) and on a thread set up as the service's inference threads
    are; interleaved frame by frame so that all three see the same machine load."""
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from models.erasenet.model import EraseNet
    from radar.simulate import simulate_sequence
    from service.inference import set_torch_threads
    from service.settings import Settings, resolve_path

    threads = Settings().inference_threads
    torch.set_num_threads(threads)
    net = EraseNet.from_checkpoints(resolve_path(model["detector"]), resolve_path(model["segmenter"]),
                                    score_threshold=model.get("score_threshold", 0.3),
                                    max_objects=model.get("max_objects", 32))
    cubes = [next(simulate_sequence("small", 1, seed=123, sequence_index=i)).cube for i in range(frames)]
    inference_thread = ThreadPoolExecutor(1, initializer=set_torch_threads, initargs=(threads,))
    net.segment(cubes[0])  # warm both threads, as the service warms its replicas
    inference_thread.submit(net.segment, cubes[0]).result()
    columns = ("plain_main_thread", "plain_inference_thread", "service")
    seconds: dict[str, dict[str, list[float]]] = {c: {s: [] for s in (*STEPS, "total")} for c in columns}
    client = []
    with httpx.Client(timeout=600) as http:
        _one(http, url, "small", _npy(cubes[0]))
        for cube in cubes:
            # a pause after each run: an OpenMP team spins for a while after its work, and the next run (in this
            # process or in the server) would otherwise share the cores with it
            timings = {"plain_main_thread": net.segment(cube).compute.seconds_by_stage()}
            time.sleep(PAUSE_S)
            threaded = inference_thread.submit(net.segment, cube).result()
            timings["plain_inference_thread"] = threaded.compute.seconds_by_stage()
            time.sleep(PAUSE_S)
            start = time.perf_counter()
            r = http.post(f"{url}/v1/segment?model=small", content=_npy(cube),
                          headers={"content-type": "application/x-npy"})
            client.append(time.perf_counter() - start)
            timings["service"] = _server_timing(r.headers["server-timing"])
            time.sleep(PAUSE_S)
            for column, timing in timings.items():
                for stage in STEPS:
                    seconds[column][stage].append(timing[stage])
                seconds[column]["total"].append(sum(timing[s] for s in STEPS))
    inference_thread.shutdown()
    rows = {stage: {f"{c}_ms": 1e3 * float(np.median(seconds[c][stage])) for c in columns}
            for stage in (*STEPS, "total")}
    for stage, row in rows.items():
        print(f"stage {stage:9s}  " + "  ".join(f"{c} {row[f'{c}_ms']:8.1f} ms" for c in columns), flush=True)
    client_p50 = float(np.median(client))
    plain_total_s = rows["total"]["plain_main_thread_ms"] / 1e3
    print(f"client p50 {client_p50 * 1e3:.1f} ms = {client_p50 / plain_total_s:.2f}x the plain process's model stages "
          f"(median {plain_total_s * 1e3:.1f} ms)", flush=True)
    return {"frames": frames, "torch_threads": threads, "median_stage_ms": rows, "client_p50_s": client_p50,
            "client_p50_over_plain_total": client_p50 / plain_total_s,
            "goal": {"client_p50_within_15pct_of_plain": client_p50 <= 1.15 * plain_total_s}}


def _upload_head(length: int, key: str | None = None) -> bytes:
    """The head of a ``POST /v1/segment`` announcing ``length`` bytes of .npy (with a key when given)."""
    auth = f"Authorization: Bearer {key}\r\n" if key else ""
    return (f"POST /v1/segment HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/x-npy\r\n{auth}"
            f"Content-Length: {length}\r\n\r\n").encode()


def _trickle(port: int, body: bytes, stop: threading.Event, rate: int, outcomes: list[int]) -> None:
    """One slow client: upload ``body`` at ``rate`` bytes/s, reconnecting whenever the server cuts it off."""
    head = _upload_head(len(body))
    while not stop.is_set():
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
                sock.sendall(head)
                for start in range(0, len(body), rate):
                    if stop.wait(1.0):
                        return
                    sock.sendall(body[start:start + rate])
                outcomes.append(int(sock.recv(64).split()[1]))
        except (OSError, IndexError, ValueError):  # cut off: the answer was 408 and the socket is closed
            outcomes.append(408)


def _normal_requests(url: str, body: bytes, clients: int, per_client: int) -> tuple[list[int], list[float]]:
    codes, latencies = [], []

    def one_client(_: int) -> None:
        with httpx.Client(timeout=120) as http:
            for _ in range(per_client):
                start = time.perf_counter()
                try:
                    code = http.post(f"{url}/v1/segment?model=small", content=body,
                                     headers={"content-type": "application/x-npy"}).status_code
                except httpx.HTTPError:
                    code = 0
                codes.append(code)
                latencies.append(time.perf_counter() - start)

    with ThreadPoolExecutor(clients) as pool:
        list(pool.map(one_client, range(clients)))
    return codes, latencies


def run_slow_clients(url: str, port: int, *, slow: int, normal_clients: int, per_client: int) -> dict:
    from radar.simulate import simulate_sequence

    body = _npy(next(simulate_sequence("small", 1, seed=3)).cube)
    idle_codes, idle = _normal_requests(url, body, normal_clients, per_client)
    stop, outcomes = threading.Event(), []
    tricklers = [threading.Thread(target=_trickle, args=(port, body, stop, 1024, outcomes)) for _ in range(slow)]
    for thread in tricklers:
        thread.start()
    time.sleep(2.0)  # every slow client is uploading
    codes, loaded = _normal_requests(url, body, normal_clients, per_client)
    stop.set()
    for thread in tricklers:
        thread.join(timeout=60)
    idle_ok = [t for t, c in zip(idle, idle_codes, strict=True) if c == 200]
    ok = [t for t, c in zip(loaded, codes, strict=True) if c == 200]
    idle_p95 = float(np.percentile(idle_ok, 95)) if idle_ok else float("nan")
    p95 = float(np.percentile(ok, 95)) if ok else float("nan")
    share = len(ok) / len(codes)
    result = {"slow_clients": slow, "slow_rate_bytes_s": 1024, "normal_clients": normal_clients,
              "normal_requests": len(codes), "idle_p95_s": idle_p95, "idle_share_200": len(idle_ok) / len(idle_codes),
              "share_200": share, "p95_s": p95, "p95_over_idle_p95": p95 / idle_p95,
              "codes": {str(c): codes.count(c) for c in sorted(set(codes))},
              "slow_client_answers": {str(c): outcomes.count(c) for c in sorted(set(outcomes))},
              "goal": {"share_200_at_least_0.95": share >= 0.95, "p95_at_most_2x_idle": p95 <= 2 * idle_p95}}
    print(f"slow clients: {slow} at 1 KB/s; normal {len(codes)} requests: {share:.1%} answered 200, p95 "
          f"{p95 * 1e3:.0f} ms against {idle_p95 * 1e3:.0f} ms idle ({result['p95_over_idle_p95']:.2f}x); slow "
          f"clients were answered {result['slow_client_answers']}", flush=True)
    return result


def run_startup(models: list[dict] | None, data_dir: Path, log: Path) -> dict:
    """Time to the first /healthz 200 and to /readyz 200 of a fresh server (the default models when ``models`` is
    None), and its logged stages."""
    import re

    port = free_port()
    env = {**os.environ, "RADARSEG_DATA_DIR": str(data_dir)}
    if models is not None:
        env["RADARSEG_MODELS"] = json.dumps(models)
    start = time.perf_counter()
    proc = subprocess.Popen(server_command(port, "info"), cwd=REPO, env=env, stdout=log.open("w"),
                            stderr=subprocess.STDOUT)
    url, healthz_s, ready_s = f"http://127.0.0.1:{port}", None, None
    try:
        with httpx.Client(timeout=2) as http:
            while ready_s is None and time.perf_counter() - start < 300 and proc.poll() is None:
                try:
                    if healthz_s is None and http.get(f"{url}/healthz").status_code == 200:
                        healthz_s = time.perf_counter() - start
                    if healthz_s is not None and http.get(f"{url}/readyz").status_code == 200:
                        ready_s = time.perf_counter() - start
                except httpx.HTTPError:
                    pass
                time.sleep(0.02 if healthz_s is None else 0.1)
    finally:
        stop_process(proc, grace_s=30)
    text = log.read_text()
    stages = {"import_and_build_s": [float(x) for x in re.findall(r"service app built in ([\d.]+) s", text)]}
    for name, load_s, warm_s in re.findall(r"model (\S+) ready: .*\(load ([\d.]+) s, warm-up ([\d.]+) s\)", text):
        stages[f"{name}_load_s"], stages[f"{name}_warmup_s"] = float(load_s), float(warm_s)
    result = {"healthz_s": healthz_s, "ready_s": ready_s, "logged_stages": stages,
              "goal": {"healthz_within_2s": healthz_s is not None and healthz_s <= 2.0,
                       "ready_within_10s_on_an_idle_machine": ready_s is not None and ready_s <= 10.0}}
    print(f"startup: /healthz after {healthz_s} s, ready after {ready_s} s; stages {stages}", flush=True)
    return result


def _hold_uploads(port: int, key: str, declared: int, stop: threading.Event, outcomes: list[int]) -> None:
    """One attacker connection: announce ``declared`` bytes, send nothing, reopen when answered."""
    head = _upload_head(declared, key)
    while not stop.is_set():
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as sock:
                sock.sendall(head)
                while not stop.is_set():
                    try:
                        answer = sock.recv(64)
                        break
                    except TimeoutError:
                        continue
                outcomes.append(int(answer.split()[1]) if answer else 0)
        except (OSError, IndexError, ValueError):
            outcomes.append(0)
            stop.wait(0.1)


def run_fairness(model: dict, data_dir: Path, log: Path, *, requests: int) -> dict:
    """Another tenant's share of 200s while one tenant holds 10 empty uploads (64 MiB + 64 KiB, then valid size)."""
    from radar.simulate import simulate_sequence

    keys = {"key-attacker-0123456789abcdef": "attacker", "key-victim-0123456789abcdefg": "victim"}
    port = free_port()
    env = {**os.environ, "RADARSEG_MODELS": json.dumps([model]), "RADARSEG_DATA_DIR": str(data_dir),
           "RADARSEG_API_KEYS": json.dumps(keys)}
    proc = subprocess.Popen(server_command(port), cwd=REPO, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    body = _npy(next(simulate_sequence("small", 1, seed=3)).cube)
    out = {}
    try:
        wait_ready(url, proc, log, timeout_s=300)
        for name, declared in (("declared_64MiB", 64 * 2**20 + 65536), ("declared_valid_length", len(body))):
            stop, outcomes = threading.Event(), []
            holders = [threading.Thread(target=_hold_uploads, args=(port, "key-attacker-0123456789abcdef", declared,
                                                                    stop, outcomes)) for _ in range(10)]
            for thread in holders:
                thread.start()
            time.sleep(1.0)
            codes = []
            with httpx.Client(timeout=120, headers={"authorization": "Bearer key-victim-0123456789abcdefg",
                                                    "content-type": "application/x-npy"}) as http:
                for _ in range(requests):
                    try:
                        codes.append(http.post(f"{url}/v1/segment?model={model['name']}", content=body).status_code)
                    except httpx.HTTPError:
                        codes.append(0)
            stop.set()
            for thread in holders:
                thread.join(timeout=60)
            share = codes.count(200) / len(codes)
            out[name] = {"declared_bytes": declared, "victim_requests": len(codes), "share_200": share,
                         "codes": {str(c): codes.count(c) for c in sorted(set(codes))},
                         "attacker_answers": {str(c): outcomes.count(c) for c in sorted(set(outcomes))},
                         "goal": {"share_200_at_least_0.95": share >= 0.95}}
            print(f"fairness ({name}): victim {share:.1%} answered 200 of {len(codes)}; attacker answered "
                  f"{out[name]['attacker_answers']}", flush=True)
    finally:
        stop_process(proc, grace_s=30)
    return out


PARTS = ("levels", "stages", "slow_clients", "startup", "fairness")


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated among {', '.join(PARTS)}")
    parser.add_argument("--requests-small", type=int, default=8, help="requests per concurrency level")
    parser.add_argument("--requests-carrada", type=int, default=4)
    parser.add_argument("--stage-frames", type=int, default=12, help="frames compared in the stages part")
    parser.add_argument("--normal-clients", type=int, default=2, help="normal clients in the slow-client part")
    parser.add_argument("--per-client", type=int, default=10, help="requests of each normal client")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 requests per level, 3 frames")
    args = parser.parse_args()
    parts = [part.strip() for part in args.parts.split(",") if part.strip()]
    if unknown := sorted(set(parts) - set(PARTS)):
        parser.error(f"unknown parts {unknown}; choose among {list(PARTS)}")

    results: dict = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    results["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(), "python": sys.version.split()[0]}
    with tempfile.TemporaryDirectory(prefix="rsg-bench-") as tmp:
        tmp = Path(tmp)
        models, kinds = _models(tmp)
        results["models"] = kinds
        for part in [p for p in parts if p in ("startup", "fairness")]:
            load_before = os.getloadavg()
            if part == "startup":
                figures = run_startup(None if kinds["small"] == "shipped checkpoints" else [models[0]],
                                      tmp / "startup-data", tmp / "startup.log")
            else:
                figures = run_fairness(models[0], tmp / "fair-data", tmp / "fair.log",
                                       requests=5 if args.quick else 20)
            figures["loadavg_before"], figures["loadavg_after"] = load_before, os.getloadavg()
            figures["cpu_flags"] = _cpu_flags()
            figures["measured_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
            results[part] = figures
        parts = [p for p in parts if p not in ("startup", "fairness")]
        proc, url = _start(models, tmp / "data", tmp / "server.log") if parts else (None, "")
        port = int(url.rsplit(":", 1)[1]) if parts else 0
        try:
            for part in parts:
                load_before = os.getloadavg()
                if part == "levels":
                    figures = run_levels(url, args)
                elif part == "stages":
                    figures = run_stages(url, models[0], 3 if args.quick else args.stage_frames)
                else:
                    figures = run_slow_clients(url, port, slow=16, normal_clients=args.normal_clients,
                                               per_client=3 if args.quick else args.per_client)
                figures["loadavg_before"], figures["loadavg_after"] = load_before, os.getloadavg()
                figures["measured_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
                results[part] = figures
        finally:
            if proc is not None:
                stop_process(proc, grace_s=30)
    if "levels" in parts:
        results.pop("target", None)  # the older layout's; now under levels
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(f"written to {RESULTS.relative_to(REPO)}")
    return results


if __name__ == "__main__":
    main()
