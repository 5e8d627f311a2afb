"""Scale-out figures: batch segmentation frames/s with 1 and 2 Ray workers, and the Ray Serve deployment's
throughput with 1 and 2 replicas at concurrency 4. Prints the figures and writes benchmarks/results/scale.json.

    .venv/bin/python benchmarks/scale.py [--frames 32 --requests 32 --rounds 2]

Ray is embedded (local, 2 CPUs) and started once. Models: the shipped checkpoints under checkpoints/ when
present, else tiny random-weight checkpoints of the ``small`` preset (score threshold 0 and 8 detections per
frame, so that region growing and the segmenter do real work). Batch segmentation reads a ``small`` store
built in-process from the simulator; every segmenter actor loads and warms its model before the clock
starts. Serve: ``service.ray_serve.RadarsegService`` with 1, then 2 replicas (1 CPU and 1 torch thread each,
one SQLite ledger), warmed up, then ``--requests`` cubes posted by 4 client threads. Configurations
alternate over ``--rounds`` rounds and the best round of each is reported with every round kept.
Our machines have 2 cores shared with other work: the 1-minute load average is recorded beside each
figure, and the ratios say as much about the load as about the code (target: >= 1.7x for
batch segmentation from 1 to 2 workers on an idle 2-core machine).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

# `python benchmarks/scale.py` puts benchmarks/ first on sys.path, where benchmarks/service.py would shadow the
# `service` package (here and in the Ray workers, which inherit the driver's sys.path).
if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
    sys.path.pop(0)

import httpx  # noqa: E402
import numpy as np  # noqa: E402
import ray  # noqa: E402
import torch  # noqa: E402

from models.checkpoint import Checkpoint, save_checkpoint  # noqa: E402
from models.registry import create_model  # noqa: E402
from pipelines.datasets.preprocess import PreprocessConfig  # noqa: E402
from pipelines.datasets.preprocess import main as preprocess  # noqa: E402
from pipelines.demo.serve_process import free_port  # noqa: E402
from pipelines.inference.segment_batch import SegmentBatchConfig, main  # noqa: E402
from pipelines.ray_runtime import init_ray  # noqa: E402
from radar.simulate import simulate_sequence  # noqa: E402
from service.settings import DEFAULT_DETECTOR, DEFAULT_SEGMENTER, resolve_path  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "scale.json"
CLASSES = ("background", "pedestrian", "cyclist", "car")
CONCURRENCY = 4


def load() -> float:
    return round(os.getloadavg()[0], 2)


def checkpoints(tmp: Path) -> dict:
    """The shipped checkpoints, or tiny random-weight ones (fixed seed)."""
    det, seg = resolve_path(DEFAULT_DETECTOR), resolve_path(DEFAULT_SEGMENTER)
    if det.is_file() and seg.is_file():
        return {"detector": str(det), "segmenter": str(seg), "kind": "shipped", "score_threshold": 0.3,
                "max_objects": 32}
    torch.manual_seed(0)
    detector = create_model("centre_detector_tiny", preset="small")
    segmenter = create_model("minkunet_tiny", preset="small")
    save_checkpoint(Checkpoint("centre_detector_tiny", {"preset": "small"}, detector.state_dict(), "small", CLASSES,
                               {"mean": 60.0, "std": 8.0}), tmp / "det.pt")
    save_checkpoint(Checkpoint("minkunet_tiny", {"preset": "small"}, segmenter.state_dict(), "small", CLASSES),
                    tmp / "seg.pt")
    return {"detector": str(tmp / "det.pt"), "segmenter": str(tmp / "seg.pt"), "kind": "tiny random weights",
            "score_threshold": 0.0, "max_objects": 8}


def build_store(out: Path, frames: int) -> Path:
    """A small-preset store, the preprocessing job run in this process (no Ray)."""
    cfg = PreprocessConfig(source="sim", out=str(out), preset="small", sequences=2, frames=frames // 2, seed=21,
                           split_fractions=(1.0, 0.0, 0.0), shard_frames=4, progress=False, in_process=True)
    return Path(preprocess(cfg)["store"])


def batch_run(store: Path, out: Path, ckpt: dict, workers: int) -> dict:
    if out.exists():
        shutil.rmtree(out)
    cfg = SegmentBatchConfig(source=f"store:{store}", detector=ckpt["detector"], segmenter=ckpt["segmenter"],
                             out=str(out), score_threshold=ckpt["score_threshold"], max_objects=ckpt["max_objects"],
                             workers=workers, shard_frames=2, progress=False)
    before = load()
    result = main(cfg)
    return {"workers": workers, "frames": result["frames"], "frames_per_second": result["frames_per_second"],
            "seconds": result["seconds_segmenting"], "load_average_1min_before": before,
            "load_average_1min_after": load()}


def serve_run(url: str, ckpt: dict, replicas: int, body: bytes, requests: int, ledger_dir: Path) -> dict:
    from ray import serve

    from service.main import create_app
    from service.ray_serve import RadarsegService

    settings = {"models": [{"name": "bench", "detector": ckpt["detector"], "segmenter": ckpt["segmenter"],
                            "score_threshold": ckpt["score_threshold"], "max_objects": ckpt["max_objects"]}],
                "torch_threads": 1, "max_queue": 4, "data_dir": str(ledger_dir)}
    deployment = RadarsegService.options(num_replicas=replicas, max_ongoing_requests=2,
                                         ray_actor_options={"num_cpus": 1})
    serve.run(deployment.bind(settings, create_app), name="radarseg", route_prefix="/",
              logging_config={"log_level": "WARNING", "enable_access_log": False})
    headers = {"content-type": "application/x-npy"}
    try:
        with httpx.Client(timeout=300) as http, ThreadPoolExecutor(CONCURRENCY) as pool:
            deadline = time.monotonic() + 300
            while http.get(f"{url}/readyz").status_code != 200:
                if time.monotonic() > deadline:
                    raise RuntimeError("Serve app not ready in 300 s")
                time.sleep(0.5)

            def post(_: int) -> float:
                start = time.perf_counter()
                r = http.post(f"{url}/v1/segment?outputs=objects", content=body, headers=headers)
                r.raise_for_status()
                return time.perf_counter() - start

            list(pool.map(post, range(2 * CONCURRENCY)))  # warm every replica and connection
            before = load()
            start = time.perf_counter()
            latencies = list(pool.map(post, range(requests)))
            seconds = time.perf_counter() - start
    finally:
        serve.delete("radarseg")
    return {"replicas": replicas, "requests": requests, "concurrency": CONCURRENCY,
            "requests_per_second": requests / seconds, "latency_p50_s": float(np.median(latencies)),
            "latency_p90_s": float(np.percentile(latencies, 90)), "load_average_1min_before": before,
            "load_average_1min_after": load()}


def best(rounds: list[dict], key: str) -> dict:
    return max(rounds, key=lambda r: r[key])


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=32, help="frames segmented per batch run")
    parser.add_argument("--requests", type=int, default=32, help="requests per Serve run")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    tmp = Path(tempfile.mkdtemp(prefix="rsg-scale-"))
    machine = {"cpu": platform.machine(), "cores": os.cpu_count(), "python": platform.python_version(),
               "ray": ray.__version__, "torch": torch.__version__, "load_average_at_start": list(os.getloadavg())}
    results: dict = {"machine": machine}
    try:
        ckpt = checkpoints(tmp)
        store = build_store(tmp / "store.zarr", args.frames)
        results["models"] = {k: ckpt[k] for k in ("kind", "score_threshold", "max_objects")}
        init_ray(None, num_cpus=2)
        batch: dict[int, list[dict]] = {1: [], 2: []}
        for _ in range(args.rounds):
            for workers in (1, 2):
                run = batch_run(store, tmp / "pred.zarr", ckpt, workers)
                batch[workers].append(run)
                print(f"batch segmentation, {workers} worker(s): {run['frames_per_second']:.2f} frames/s "
                      f"(load {run['load_average_1min_before']})", flush=True)
        one, two = best(batch[1], "frames_per_second"), best(batch[2], "frames_per_second")
        results["batch_segmentation"] = {
            "preset": "small", "frames": args.frames, "shard_frames": 2,
            "frames_per_second_1_worker": one["frames_per_second"],
            "frames_per_second_2_workers": two["frames_per_second"],
            "speedup_2_vs_1": two["frames_per_second"] / one["frames_per_second"],
            "rounds": batch,
        }

        from ray import serve

        port = free_port()
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        body = io.BytesIO()
        np.save(body, next(simulate_sequence("small", 1, seed=2)).cube)
        serving: dict[int, list[dict]] = {1: [], 2: []}
        for _ in range(args.rounds):
            for replicas in (1, 2):
                run = serve_run(f"http://127.0.0.1:{port}", ckpt, replicas, body.getvalue(), args.requests,
                                tmp / f"ledger-{replicas}")
                serving[replicas].append(run)
                print(f"Ray Serve, {replicas} replica(s), concurrency {CONCURRENCY}: "
                      f"{run['requests_per_second']:.2f} requests/s, p50 {run['latency_p50_s'] * 1e3:.0f} ms "
                      f"(load {run['load_average_1min_before']})", flush=True)
        serve.shutdown()
        one, two = best(serving[1], "requests_per_second"), best(serving[2], "requests_per_second")
        results["serve"] = {
            "concurrency": CONCURRENCY, "requests": args.requests,
            "requests_per_second_1_replica": one["requests_per_second"],
            "requests_per_second_2_replicas": two["requests_per_second"],
            "speedup_2_vs_1": two["requests_per_second"] / one["requests_per_second"],
            "rounds": serving,
        }
    finally:
        if ray.is_initialized():
            ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)
    results["machine"]["load_average_at_end"] = list(os.getloadavg())
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"batch segmentation 2 vs 1 workers: {results['batch_segmentation']['speedup_2_vs_1']:.2f}x; "
          f"Serve 2 vs 1 replicas: {results['serve']['speedup_2_vs_1']:.2f}x; written to {args.out}")


if __name__ == "__main__":
    main_bench()
