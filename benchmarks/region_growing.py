"""Region growing against the detector it follows: median ms per frame of `grow_regions` (seeded at the true
centres, as a trained detector seeds it) and of the shipped detector architecture in its inference form
(`FrozenDetector`: BatchNorms folded, channels_last, traced), interleaved in one loop, one thread, at `small` and
`carrada`. The goal is growing in at most a quarter of the detector's time. Prints the figures and writes
benchmarks/results/region_growing.json with the load average; never asserts a time.

    .venv/bin/python -m benchmarks.region_growing [--frames 6] [--repeats 4]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from models.checkpoint import load_checkpoint
from models.detector.inference import FrozenDetector
from models.registry import create_model
from radar.region_growing import grow_regions
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "region_growing.json"


def measure(preset: str, n_frames: int, repeats: int) -> dict:
    """Median / min seconds of the detector's forward and of region growing, measured alternately."""
    frames = [f for f in simulate_sequence(preset, n_frames, seed=5) if f.objects]
    cases = [(f.log_power(), np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin]
                                       for o in f.objects if o.n_voxels], float).reshape(-1, 3)) for f in frames]
    profile = frames[0].profile
    n_range, n_angle, n_doppler = profile.shape
    det = load_checkpoint(REPO / "checkpoints" / "detector.pt")
    torch.manual_seed(0)
    detector = create_model(det.model_name, **{**det.config, "preset": preset}).eval()
    frozen = FrozenDetector(detector, (1, n_doppler, n_range, n_angle))
    x = torch.randn(1, n_doppler, n_range, n_angle)
    times: dict[str, list[float]] = {"detector": [], "grow": []}
    roi_voxels = []
    with torch.inference_mode():
        frozen(x)  # warm-up
        for _ in range(repeats):
            for log_power, seeds in cases:
                start = time.perf_counter()
                frozen(x)
                times["detector"].append(time.perf_counter() - start)
                start = time.perf_counter()
                regions = grow_regions(log_power, seeds, profile)
                times["grow"].append(time.perf_counter() - start)
                roi_voxels.append(len(regions))
    out = {name: {"median_s": statistics.median(t), "min_s": min(t)} for name, t in times.items()}
    out["grow_over_detector"] = out["grow"]["median_s"] / out["detector"]["median_s"]
    out["roi_voxels_mean"] = float(np.mean(roi_voxels))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = {"load_average_before": os.getloadavg(), "threads": 1, "presets": {}}
    for preset in ("small", "carrada"):
        row = measure(preset, args.frames, args.repeats)
        results["presets"][preset] = row
        print(f"{preset:8} grow {row['grow']['median_s'] * 1e3:6.2f} ms (min {row['grow']['min_s'] * 1e3:.2f})  "
              f"detector {row['detector']['median_s'] * 1e3:6.2f} ms (min {row['detector']['min_s'] * 1e3:.2f})  "
              f"grow / detector {row['grow_over_detector']:.2f}  ({row['roi_voxels_mean']:.0f} ROI voxels)")
    results["load_average_after"] = os.getloadavg()
    print(f"load average {results['load_average_before'][0]:.2f} -> {results['load_average_after'][0]:.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
