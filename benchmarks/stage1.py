"""Stage 1 side by side: detector forward, region growing and CFAR per frame, each as a ratio to the
log transform of the same cube (the floor every method pays), and a D_thresh sweep of region growing
(visited points and recall, seeded at true centres) like the paper's table (docs/design.md section 6).
Prints tables and writes benchmarks/results/stage1.json.

    .venv/bin/python -m benchmarks.stage1 [--frames 4] [--sweep-frames 3] [--threads 1]

Target: region growing at most 10% of the detector's forward time. The detector is
untrained here (its cost does not depend on its weights); region growing is seeded at the true
centres so that its cost and recall are those of a detector that finds every object.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import Table, int_options_main
from models.registry import create_model
from radar.cfar import cfar_centres
from radar.profiles import get_profile
from radar.region_growing import RegionGrowingConfig, grow_regions
from radar.simulate import simulate_sequence
from radar.transforms import log_power

PAPER_SWEEP = {3: (20731, 0.901), 4: (41579, 0.946), 5: (66527, 0.958), 6: (94504, 0.962), 7: (126127, 0.965),
               8: (160323, 0.967)}
RESULTS = Path(__file__).resolve().parent / "results" / "stage1.json"


def _seeds(frame) -> np.ndarray:
    return np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels])


def _best_of(fn, *args, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return min(times)


def stage_times(preset: str, n_frames: int) -> dict:
    profile = get_profile(preset)
    detector = create_model("centre_detector", preset=preset).eval()
    rows = []
    for frame in simulate_sequence(preset, n_frames, seed=17):
        lp = log_power(frame.cube)
        x = torch.from_numpy(np.ascontiguousarray(lp.transpose(2, 0, 1)))[None]  # (1, D, R, A)
        with torch.no_grad():
            detector(x)  # warm-up
            t_detect = _best_of(detector, x)
        seeds = _seeds(frame)
        regions = grow_regions(lp, seeds, profile)
        rows.append({
            "log_transform_s": _best_of(log_power, frame.cube),
            "detector_s": t_detect,
            "region_growing_s": _best_of(grow_regions, lp, seeds, profile),
            "cfar_s": _best_of(cfar_centres, lp, profile),
            "visited": regions.visited, "roi_voxels": len(regions), "recall": regions.recall(frame.instances),
            "objects": len(seeds),
        })
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    floor = mean["log_transform_s"]
    return {**mean, "frames": n_frames, "cube_voxels": int(np.prod(profile.shape)),
            "ratio_to_log_transform": {k: mean[f"{k}_s"] / floor for k in ("detector", "region_growing", "cfar")},
            "region_growing_over_detector": mean["region_growing_s"] / mean["detector_s"],
            "config": RegionGrowingConfig.for_profile(profile).__dict__}


def sweep(preset: str, n_frames: int, distances=(3, 4, 5, 6, 7, 8)) -> dict:
    profile = get_profile(preset)
    frames = [(log_power(f.cube), _seeds(f), f.instances) for f in simulate_sequence(preset, n_frames, seed=29)]
    out = {}
    for d in distances:
        config = RegionGrowingConfig.for_profile(profile, distance_m=float(d))
        results = [grow_regions(lp, seeds, profile, config) for lp, seeds, _ in frames]
        out[d] = {"visited": float(np.mean([r.visited for r in results])),
                  "roi_voxels": float(np.mean([len(r) for r in results])),
                  "recall": float(np.mean([r.recall(inst) for r, (_, _, inst) in zip(results, frames, strict=True)]))}
    return out


PRESETS = Table((("preset", "8"), ("log tf ms", "9.1f"), ("detector", "9.1f"), ("grow", "7.1f"), ("cfar", "7.1f"),
                 ("grow/det", "8.1%"), ("visited", "8.0f"), ("roi", "7.0f"), ("recall", "6.3f")))


def run(frames: int, sweep_frames: int, threads: int) -> dict:
    """Each preset's stage times over ``frames`` frames and the D_thresh sweep over ``sweep_frames``."""
    torch.set_num_threads(threads)
    return {"threads": threads,
            "presets": {preset: stage_times(preset, frames) for preset in ("small", "carrada", "nxp")},
            "sweep": {preset: sweep(preset, sweep_frames) for preset in ("nxp", "carrada")},
            "paper_sweep_nxp": PAPER_SWEEP}


def report(results: dict) -> None:
    print(PRESETS.header())
    for preset, r in results["presets"].items():
        print(PRESETS.row(preset, r["log_transform_s"] * 1e3, r["detector_s"] * 1e3, r["region_growing_s"] * 1e3,
                          r["cfar_s"] * 1e3, r["region_growing_over_detector"], r["visited"], r["roi_voxels"],
                          r["recall"]))
    print("\nD_thresh sweep (seeded at true centres): visited / recall; paper (NXP) in brackets")
    for d, row in results["sweep"]["nxp"].items():
        paper = PAPER_SWEEP[d]
        car = results["sweep"]["carrada"][d]
        print(f"  {d} m  nxp {row['visited']:8.0f} / {row['recall']:.3f}   [{paper[0]:6d} / {paper[1]:.3f}]"
              f"   carrada {car['visited']:8.0f} / {car['recall']:.3f}")


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, report=report, frames=4, sweep_frames=3, threads=1)


if __name__ == "__main__":
    raise SystemExit(main())
