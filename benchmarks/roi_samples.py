"""What a segmenter training sample costs to make at a store's radar: the frame read, region growing from the true
centres, the ROI points, and the model's step on it, side by side; and the frame read in the stored (R, A, D)
layout (what :class:`pipelines.training.segmenter.RoiDataset` reads) against the model's (D, R, A) layout
transposed back (what it read before).

    .venv/bin/python -m benchmarks.roi_samples --store STORE.zarr [--frames 12] [--threads 1] [--batch-size 2]

Thread CPU seconds, medians over the frames (the layouts interleaved frame by frame). Writes
benchmarks/results/roi_samples.json; never asserts a time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from benchmarks.harness import machine, write_with_load
from models.registry import create_model
from pipelines.datasets.store import StoreDataset
from pipelines.datasets.store_info import StoreInfo
from pipelines.evaluation.scoring import frame_centres
from pipelines.training.config import RECIPES
from pipelines.training.segmenter import collate_roi
from radar.region_growing import grow_regions
from radar.roi import roi_points

RESULTS = Path(__file__).parent / "results" / "roi_samples.json"


def _timed(call):
    started = time.thread_time()
    value = call()
    return value, time.thread_time() - started


def run(store_path: str, frames: int, threads: int, batch_size: int) -> dict:
    torch.set_num_threads(threads)
    store = StoreInfo.read(store_path)
    profile = store.profile
    stored = StoreDataset(store_path, "train", fields=("input", "labels", "objects"), normalise=False,
                          doppler_last=True)
    transposed = StoreDataset(store_path, "train", fields=("input", "labels", "objects"), normalise=False)
    slots = [i for i in range(len(stored)) if int(stored[i]["n_objects"]) > 0][:frames]
    figures: dict[str, list[float]] = {k: [] for k in ("read_stored", "read_transposed", "grow", "grow_transposed",
                                                       "points")}
    samples, voxels_per_roi = [], []
    for i in slots:
        sample, seconds = _timed(lambda i=i: stored[i])
        figures["read_stored"].append(seconds)
        old, seconds = _timed(lambda i=i: transposed[i])
        figures["read_transposed"].append(seconds)
        old_cube = old["input"].permute(1, 2, 0).numpy()  # (R, A, D), a view: what the ROI samples grew from
        _, seconds = _timed(lambda c=old_cube, s=old: grow_regions(c, frame_centres(s), profile))
        figures["grow_transposed"].append(seconds)
        cube = sample["input"].numpy()
        regions, seconds = _timed(lambda c=cube, s=sample: grow_regions(c, frame_centres(s), profile))
        figures["grow"].append(seconds)
        voxels = regions.voxels if len(regions) else regions.seeds
        points, seconds = _timed(lambda v=voxels, c=cube: roi_points(v, c, profile, mean_db=store.normalisation["mean"],
                                                                     std_db=store.normalisation["std"]))
        figures["points"].append(seconds)
        voxels_per_roi.append(len(voxels))
        samples.append({"coords": torch.from_numpy(points.coords), "features": torch.from_numpy(points.features),
                        "labels": torch.from_numpy(sample["labels"].numpy()[tuple(voxels.T)].astype(np.int64)),
                        "recall": 1.0, "frame": i})
    hyper = RECIPES["segmenter"]["crops"]
    model = create_model(hyper.model, preset=profile, **hyper.model_config).train()
    optimizer = torch.optim.SGD(model.parameters(), lr=hyper.lr, momentum=0.9, nesterov=True)
    steps = []
    for start in range(0, len(samples) - batch_size + 1, batch_size):
        batch = collate_roi(samples[start:start + batch_size])

        def step(batch=batch) -> None:
            optimizer.zero_grad(set_to_none=True)
            logits = model(model.make_input(batch["coords"], batch["features"]))
            nn.functional.cross_entropy(logits, batch["labels"]).backward()
            optimizer.step()

        steps.append(_timed(step)[1])
    medians = {name: statistics.median(values) for name, values in figures.items()}
    sample_s = medians["read_stored"] + medians["grow"] + medians["points"]
    before_s = medians["read_transposed"] + medians["grow_transposed"] + medians["points"]
    return {"store": store_path, "preset": profile.name, "frames": len(slots), "threads": threads,
            "batch_size": batch_size, "cpu_s_median": medians, "sample_cpu_s": sample_s,
            "sample_cpu_s_transposed": before_s, "sample_speedup": before_s / sample_s,
            "step_cpu_s_median": statistics.median(steps[1:] or steps),
            "roi_voxels_median": float(np.median(voxels_per_roi)), "machine": machine(),
            "load_average_before": os.getloadavg()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch-size", type=int, default=RECIPES["segmenter"]["crops"].batch_size)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if min(args.frames, args.threads, args.batch_size) < 1 or args.frames < args.batch_size:
        parser.error("--frames, --threads and --batch-size must be >= 1, and --frames >= --batch-size")
    result = run(args.store, args.frames, args.threads, args.batch_size)
    for name, seconds in result["cpu_s_median"].items():
        print(f"{name:16s} {seconds * 1e3:8.1f} ms")
    print(f"a ROI sample {result['sample_cpu_s'] * 1e3:.0f} ms (transposed layout "
          f"{result['sample_cpu_s_transposed'] * 1e3:.0f} ms, {result['sample_speedup']:.2f}x)")
    print(f"a step of {result['batch_size']} ROIs {result['step_cpu_s_median'] * 1e3:.0f} ms; "
          f"{result['roi_voxels_median']:.0f} voxels a ROI (median); {result['preset']}, "
          f"flags {' '.join(result['machine']['flags'])}")
    write_with_load(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
