"""The tracker's cost (radar/tracking.py): ms per ``Tracker.step`` with 5, 10, 15 and 30 objects a frame, at the
`small` preset's defaults (``TrackerConfig.for_profile``). Objects move at constant velocity inside a 40 x 40 m box
in front of the radar (bouncing off its walls), measured with 0.3 m of position noise and 0.3 m/s of radial
velocity noise, every frame; the first 5 frames (tracks starting) are not timed. One thread, numpy and scipy as
installed. The issue's goal is <= 1 ms per frame. Prints the figures and writes benchmarks/results/tracking.json
with the load average and the CPU model; never asserts a time.

    .venv/bin/python -m benchmarks.tracking [--frames 300]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from radar.profiles import get_profile
from radar.tracking import Measurements, Tracker, TrackerConfig

RESULTS = Path(__file__).parent / "results" / "tracking.json"
COUNTS = (5, 10, 15, 30)  # the goal of <= 1 ms a frame is stated for 10 objects
WARMUP_FRAMES = 5


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def scene(n_objects: int, n_frames: int, period_s: float, seed: int = 0) -> list[Measurements]:
    """Noisy measurements of ``n_objects`` objects over ``n_frames`` frames."""
    rng = np.random.default_rng(seed)
    low, high = np.array([-20.0, 5.0]), np.array([20.0, 45.0])
    position = rng.uniform(low, high, (n_objects, 2))
    velocity = rng.uniform(-4.0, 4.0, (n_objects, 2))
    classes = rng.integers(1, 4, n_objects)
    frames = []
    for _ in range(n_frames):
        position = position + velocity * period_s
        out = (position < low) | (position > high)
        velocity[out] = -velocity[out]
        position = np.clip(position, low, high)
        r = np.hypot(position[:, 0], position[:, 1])
        radial = (position * velocity).sum(1) / r
        frames.append(Measurements(position[:, 0] + rng.normal(0, 0.3, n_objects),
                                   position[:, 1] + rng.normal(0, 0.3, n_objects),
                                   radial + rng.normal(0, 0.3, n_objects), classes, rng.uniform(0.3, 1.0, n_objects)))
    return frames


def measure(n_objects: int, n_frames: int, config: TrackerConfig) -> dict:
    frames = scene(n_objects, n_frames, config.frame_period_s, seed=n_objects)
    tracker = Tracker(config)
    ms, alive = [], []
    for k, measurements in enumerate(frames):
        start = time.perf_counter()
        step = tracker.step(measurements)
        elapsed = time.perf_counter() - start
        if k >= WARMUP_FRAMES:
            ms.append(1e3 * elapsed)
            alive.append(len(step.tracks))
    a = np.asarray(ms)
    return {"objects": n_objects, "frames_timed": len(a), "median_ms": float(np.median(a)),
            "p99_ms": float(np.percentile(a, 99)), "mean_ms": float(a.mean()), "max_ms": float(a.max()),
            "tracks_alive_mean": float(np.mean(alive)), "tracks_started": tracker.next_id - 1}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    config = TrackerConfig.for_profile(get_profile("small"))
    results = {"load_average_before": os.getloadavg(), "cpu_model": cpu_model(), "cpus": os.cpu_count(),
               "python": platform.python_version(), "numpy": np.__version__, "preset": "small",
               "config": config.to_dict(), "goal_ms_per_frame": 1.0, "rows": []}
    for n in COUNTS:
        row = measure(n, args.frames, config)
        results["rows"].append(row)
        print(f"{n:3d} objects: median {row['median_ms']:.3f} ms, p99 {row['p99_ms']:.3f} ms per frame "
              f"({row['tracks_alive_mean']:.1f} tracks alive, {row['tracks_started']} started)")
    results["load_average_after"] = os.getloadavg()
    print(f"load average {results['load_average_before'][0]:.2f} -> {results['load_average_after'][0]:.2f}; "
          f"{results['cpu_model']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
