"""NXP-size cubes end to end: simulate, preprocess, segment and serve a 424 x 512 x 104 cube (preset ``nxp``).

    .venv/bin/python -m benchmarks.nxp_scale [--frames 2] [--skip-serve]

No pair is trained for ``nxp``: the models are the shipped pair's architectures (``checkpoints/detector.pt`` and
``segmenter.pt``, built for ``nxp``) with random weights (seed 0), served with score threshold 0 and 8 seeds a
frame, so that region growing and the segmenter do real work (their ROI sizes are those of random seeds, not of a
trained detector's). Figures, one thread:

- simulate: seconds a frame of ``radar.simulate``;
- preprocess: an in-process store of ``--frames`` frames (``pipelines.datasets.preprocess``): seconds, frames/s,
  bytes on disk a frame;
- segment: the torch engine on one frame's complex cube (with its earlier frame as history): seconds by stage and
  the peak RSS growth of this process over the frame (VmHWM reset before it, /proc/self/clear_refs);
- serve: a real ``radarseg serve`` (uvicorn) with ``max_body_bytes`` raised to hold the complex64 body (the service
  refuses at start-up a model whose complex64 cube does not fit): one float16 log-power cube (43 MiB) and one
  complex64 cube (172 MiB) posted with Content-Length; per body the server's RSS before, its peak over the request
  (VmHWM reset first) and peak growth over the body's bytes (goal: <= 3x), and the 413 a body past the limit gets.

Writes benchmarks/results/nxp_scale.json with the CPU's flags and the load average before and after.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import resource
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import torch

from benchmarks.harness import machine, write_with_load
from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.registry import create_model
from radar import transforms
from radar.profiles import get_profile

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "nxp_scale.json"
PRESET = "nxp"
SEED = 4242
SERVED = {"score_threshold": 0.0, "max_objects": 8}
MIB = 2**20


def rss_mib(pid: int | str = "self") -> dict[str, float]:
    """VmRSS (now) and VmHWM (peak since start or the last reset) of a process, MiB."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024
    return fields


def reset_peak(pid: int | str = "self") -> None:
    """Reset a process's VmHWM to its current RSS (Linux: ``5`` into /proc/PID/clear_refs)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def random_pair(out: Path) -> tuple[Path, Path]:
    """The shipped pair's architectures built for ``nxp``, random weights (seed 0), saved as checkpoints."""
    profile = get_profile(PRESET)
    torch.manual_seed(0)
    paths = []
    for stage in ("detector", "segmenter"):
        shipped = load_checkpoint(ROOT / "checkpoints" / f"{stage}.pt")
        config = {**shipped.config, "preset": PRESET}
        model = create_model(shipped.model_name, **config)
        checkpoint = Checkpoint(model_name=shipped.model_name, config=config, state_dict=model.state_dict(),
                                preset=PRESET, class_names=tuple(profile.all_class_names),
                                normalisation=dict(shipped.normalisation), extra={"stage": stage})
        paths.append(save_checkpoint(checkpoint, out / f"{stage}-nxp-random.pt"))
    return paths[0], paths[1]


def simulate_figures(frames: int) -> tuple[dict, list[np.ndarray]]:
    from radar.simulate import simulate_sequence

    started = time.perf_counter()
    cubes = [frame.cube for frame in simulate_sequence(PRESET, frames, seed=SEED)]
    seconds = time.perf_counter() - started
    return {"frames": frames, "seconds_per_frame": seconds / frames, "cube_shape": list(cubes[0].shape),
            "cube_dtype": cubes[0].dtype.name,
            "complex64_mib": cubes[0].astype(np.complex64).nbytes / MIB,
            "float16_log_power_mib": cubes[0].size * 2 / MIB}, cubes


def preprocess_figures(out: Path, frames: int) -> dict:
    from pipelines.datasets.preprocess import PreprocessConfig
    from pipelines.datasets.preprocess import main as preprocess

    store = out / "nxp.zarr"
    started = time.perf_counter()
    preprocess(PreprocessConfig(source="sim", out=str(store), preset=PRESET, sequences=1, frames=frames, seed=SEED,
                                split_fractions=(1.0, 0.0, 0.0), shard_frames=frames, progress=False,
                                in_process=True))
    seconds = time.perf_counter() - started
    size = sum(p.stat().st_size for p in store.rglob("*") if p.is_file())
    return {"frames": frames, "seconds": seconds, "frames_per_second": frames / seconds,
            "store_bytes": size, "store_mib_per_frame": size / frames / MIB}


def segment_figures(detector: Path, segmenter: Path, cubes: list[np.ndarray]) -> dict:
    """The torch engine on the last cube (the one before it as history): warm-up run, then the timed one."""
    from models.runtime import load_erasenet

    net = load_erasenet(detector, segmenter, **SERVED)
    history = [transforms.log_power(cubes[-2])] if net.history_frames and len(cubes) > 1 else None
    net.segment(cubes[-1], history=history)  # warm-up: the first call of each path traces
    reset_peak()
    before = rss_mib()["VmRSS"]
    started = time.perf_counter()
    result = net.segment(cubes[-1], history=history)
    seconds = time.perf_counter() - started
    peak = rss_mib()["VmHWM"]
    complex_mib = cubes[-1].astype(np.complex64).nbytes / MIB
    return {"engine": "torch", "history_frames": net.history_frames, "seconds": seconds,
            "seconds_by_stage": result.compute.seconds, "roi_voxels": len(result.regions),
            "detections": len(result.centres), "rss_before_mib": before, "peak_rss_mib": peak,
            "peak_growth_mib": peak - before, "peak_growth_over_complex64_bytes": (peak - before) / complex_mib}


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def post_measured(http: httpx.Client, pid: int, body: bytes, kind: str) -> dict:
    """One body posted (after one warm-up post of it): status, seconds, the server's RSS and peak over it."""
    headers = {"content-type": "application/x-npy"}
    http.post(f"/v1/segment?input={kind}&outputs=objects", content=body, headers=headers)
    reset_peak(pid)
    before = rss_mib(pid)["VmRSS"]
    started = time.perf_counter()
    answer = http.post(f"/v1/segment?input={kind}&outputs=objects", content=body, headers=headers)
    seconds = time.perf_counter() - started
    peak = rss_mib(pid)["VmHWM"]
    body_mib = len(body) / MIB
    return {"input": kind, "status": answer.status_code, "body_mib": body_mib, "seconds": seconds,
            "rss_before_mib": before, "peak_rss_mib": peak, "peak_growth_mib": peak - before,
            "peak_growth_over_body": (peak - before) / body_mib,
            "detail": None if answer.status_code == 200 else answer.text[:300]}


def serve_figures(detector: Path, segmenter: Path, cube: np.ndarray, out: Path) -> dict:
    from pipelines.demo.serve_process import free_port, serve_command, stop_process, wait_ready

    complex_body = npy(cube.astype(np.complex64))
    log_power_body = npy(transforms.log_power(cube).astype(np.float16))
    limit = len(complex_body) + 65536
    models = [{"name": "nxp-random", "detector": str(detector), "segmenter": str(segmenter), **SERVED}]
    env = {**os.environ, "RADARSEG_MODELS": json.dumps(models), "RADARSEG_MAX_BODY_BYTES": str(limit),
           "RADARSEG_MAX_UPLOAD_BYTES": str(2 * limit), "RADARSEG_MAX_TENANT_UPLOAD_BYTES": str(2 * limit),
           "RADARSEG_DATA_DIR": str(out / "data"), "RADARSEG_WARMUP": "false", "OMP_NUM_THREADS": "1",
           "PYTHONUNBUFFERED": "1"}
    port = free_port()
    log_path = out / "serve.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(serve_command(port), cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        started = time.perf_counter()
        wait_ready(f"http://127.0.0.1:{port}", proc, log_path, timeout_s=600)
        ready_seconds = time.perf_counter() - started
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=600) as http:
            bodies = [post_measured(http, proc.pid, log_power_body, "log_power"),
                      post_measured(http, proc.pid, complex_body, "complex")]
        past_the_limit = declared_only(port, limit + 1)
    finally:
        stop_process(proc)
    return {"max_body_bytes": limit, "ready_seconds": ready_seconds, "bodies": bodies,
            "past_the_limit": past_the_limit}


def declared_only(port: int, length: int) -> str:
    """The status line and body of the answer to a request head declaring ``length`` bytes, none of them sent."""
    with socket.create_connection(("127.0.0.1", port), timeout=60) as connection:
        connection.sendall(f"POST /v1/segment HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/x-npy\r\n"
                           f"Content-Length: {length}\r\n\r\n".encode())
        answer = b""
        while b"\r\n\r\n" not in answer or not answer.rstrip().endswith(b"}"):
            chunk = connection.recv(65536)
            if not chunk:
                break
            answer += chunk
    head, _, body = answer.decode(errors="replace").partition("\r\n\r\n")
    return f"{head.splitlines()[0] if head else ''} {body[:300]}"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2, help="frames simulated and preprocessed (>= 2)")
    parser.add_argument("--skip-serve", action="store_true", help="no uvicorn figures")
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error("--frames must be >= 2 (the segmented frame reads the one before)")
    torch.set_num_threads(1)
    results: dict = {"machine": machine(), "load_average_before": os.getloadavg(), "threads": 1, "preset": PRESET,
                     "models": "the shipped pair's architectures built for nxp, random weights (seed 0); "
                               f"served with {SERVED}"}
    with tempfile.TemporaryDirectory(prefix="nxp-scale-") as scratch:
        out = Path(scratch)
        results["simulate"], cubes = simulate_figures(args.frames)
        print("simulate", json.dumps(results["simulate"]), flush=True)
        results["preprocess"] = preprocess_figures(out, args.frames)
        print("preprocess", json.dumps(results["preprocess"]), flush=True)
        detector, segmenter = random_pair(out)
        results["segment"] = segment_figures(detector, segmenter, cubes)
        print("segment", json.dumps(results["segment"]), flush=True)
        if not args.skip_serve:
            results["serve"] = serve_figures(detector, segmenter, cubes[-1], out)
            print("serve", json.dumps(results["serve"]), flush=True)
    results["benchmark_peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    write_with_load(results, args.out)
    return results


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
