"""Preprocessing throughput with 1 and 2 Ray workers (shard tasks in flight) on the ``small`` and
``carrada`` presets, bytes on disk per frame per array, and the read throughput of the training
Dataset against the centre detector's training step rate. Prints the figures and writes
benchmarks/results/preprocess.json.

    .venv/bin/python benchmarks/preprocess.py [--frames-small 64 --frames-carrada 16]

Source: the simulator, run inside the Ray tasks (simulation is part of the measured work). Ray is
embedded (local, 2 CPUs) and started once; its workers are warmed up (imports) before timing.
Targets: 2 workers >= 1.7x one worker; Dataset reads >= 5x the detector's training rate.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import ray
import torch

from models.detector.targets import build_centre_targets
from models.registry import create_model
from pipelines.datasets.preprocess import PreprocessConfig, main
from pipelines.datasets.store import CENTRE_COLUMNS, StoreDataset
from pipelines.ray_runtime import init_ray

RESULTS = Path(__file__).parent / "results" / "preprocess.json"


def run_job(out: Path, preset: str, frames: int, shard_frames: int, tasks: int) -> dict:
    if out.exists():
        shutil.rmtree(out)
    cfg = PreprocessConfig(source="sim", out=str(out), preset=preset, sequences=2, frames=frames // 2, seed=1,
                           tasks=tasks, shard_frames=shard_frames, progress=False)
    return main(cfg)


def bytes_per_frame(store: Path, n_frames: int) -> dict[str, float]:
    sizes = {}
    for array in sorted(p for p in store.iterdir() if p.is_dir() and p.name != "progress"):
        sizes[array.name] = sum(f.stat().st_size for f in array.rglob("*") if f.is_file()) / n_frames
    return sizes


def read_rate(store: Path, fields: tuple[str, ...], passes: int = 2) -> float:
    ds = StoreDataset(store, None, fields=fields, flip_prob=0.5)
    ds[0]  # open the arrays
    start = time.perf_counter()
    for _ in range(passes):
        for i in np.random.default_rng(0).permutation(len(ds)):
            ds[int(i)]
    return passes * len(ds) / (time.perf_counter() - start)


def detector_train_rate(store: Path, batch_size: int = 8, steps: int = 3) -> float:
    """Frames/s of full training steps (forward, loss, backward, Adam) of the centre detector on ``small``."""
    torch.manual_seed(0)
    model = create_model("centre_detector", preset="small")
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    ds = StoreDataset(store, None, fields=("input", "heatmap"))
    batch = [ds[i % len(ds)] for i in range(batch_size)]
    inputs = torch.stack([s["input"] for s in batch])
    centres = [s["objects"][: int(s["n_objects"])][:, CENTRE_COLUMNS]
               .double().numpy() for s in batch]
    targets = build_centre_targets(centres, (128, 128))

    def step() -> None:
        optimiser.zero_grad()
        losses = model.compute_loss(model(inputs), targets)
        sum(losses.values()).backward()
        optimiser.step()

    step()  # warm-up
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * batch_size / (time.perf_counter() - start)


def main_bench() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames-small", type=int, default=64)
    parser.add_argument("--frames-carrada", type=int, default=16)
    args = parser.parse_args()
    init_ray(None, num_cpus=2)
    work = Path(tempfile.mkdtemp(prefix="bench-preprocess-"))
    machine = {"cpu": platform.machine(), "cores": os.cpu_count(), "python": platform.python_version(),
               "ray": ray.__version__, "load_average_at_start": os.getloadavg()}
    results: dict = {"machine": machine,
                     "source": "sim (simulated inside the Ray tasks)", "presets": {}}
    try:
        run_job(work / "warmup.zarr", "small", 4, 1, 2)  # both workers import the pipeline once
        for preset, frames, shard_frames in (("small", args.frames_small, 4), ("carrada", args.frames_carrada, 2)):
            entry: dict = {"frames": frames, "shard_frames": shard_frames}
            for tasks in (1, 2):
                result = run_job(work / f"{preset}-{tasks}.zarr", preset, frames, shard_frames, tasks)
                entry[f"frames_per_second_{tasks}_worker{'s' if tasks > 1 else ''}"] = result["frames_per_second"]
                print(f"{preset}: {tasks} worker(s): {result['frames_per_second']:.2f} frames/s "
                      f"({result['seconds_shards']:.2f} s for {frames} frames)")
            entry["speedup_2_vs_1"] = entry["frames_per_second_2_workers"] / entry["frames_per_second_1_worker"]
            entry["bytes_per_frame"] = bytes_per_frame(work / f"{preset}-2.zarr", frames)
            entry["raw_cube_bytes_complex64"] = int(np.prod(ray_shape(preset))) * 8
            print(f"{preset}: speed-up {entry['speedup_2_vs_1']:.2f}x (target >= 1.7x); bytes/frame: "
                  + ", ".join(f"{k} {v:,.0f}" for k, v in entry["bytes_per_frame"].items()))
            results["presets"][preset] = entry
        store = work / "small-2.zarr"
        train_rate = detector_train_rate(store)
        reads = {"all_fields": read_rate(store, StoreDataset.ALL_FIELDS),
                 "detector_fields": read_rate(store, ("input", "heatmap"))}
        results["dataset"] = {
            "preset": "small", "read_frames_per_second": reads,
            "detector_train_frames_per_second": train_rate, "detector_batch_size": 8,
            "ratio_detector_fields_vs_training": reads["detector_fields"] / train_rate,
            "ratio_all_fields_vs_training": reads["all_fields"] / train_rate,
        }
        print(f"Dataset reads (small, one process, random order, flips): {reads['all_fields']:.1f} frames/s all "
              f"fields, {reads['detector_fields']:.1f} frames/s detector fields; detector training "
              f"{train_rate:.1f} frames/s -> {results['dataset']['ratio_detector_fields_vs_training']:.1f}x "
              "(target >= 5x)")
    finally:
        ray.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    print(f"written {RESULTS}")
    return results


def ray_shape(preset: str) -> tuple[int, int, int]:
    from radar.profiles import get_profile

    return get_profile(preset).shape


if __name__ == "__main__":
    main_bench()
