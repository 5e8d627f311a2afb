"""End-to-end ERASE-Net inference per frame: time and MACs of every stage on `small` and `carrada`
frames, with the paper-size networks (detector "slim_sep", MinkUNet / SPVCNN ratio 0.37).
Prints a table and writes benchmarks/results/end_to_end.json.

    .venv/bin/python benchmarks/end_to_end.py [--frames 3] [--threads 2]

Weights are random (cost does not depend on them). Two passes per frame: the detector's own top-K
seeds (K = number of true objects, threshold 0), and seeds at the true centres, which give the ROI a
trained detector would grow. Paper (CARRADA): 8.41 G (MinkUNet) / 9.3 G (SPVCNN) + 0.49 G detector.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from models.erasenet.model import STEPS, EraseNet
from models.registry import create_model
from radar.centres import Centres
from radar.simulate import simulate_sequence


def run(preset: str, segmenter: str, n_frames: int) -> dict:
    torch.manual_seed(0)
    frames = list(simulate_sequence(preset, n_frames, seed=5))
    lp0 = frames[0].log_power()
    net = EraseNet(create_model("centre_detector", preset=preset), create_model(segmenter, preset=preset), preset,
                   mean_db=float(lp0.mean()), std_db=float(lp0.std()), score_threshold=0.0)
    net.segment(frames[0].cube)  # warm-up: meta copy of the detector for its MAC count, first maps
    rows = {"detector_seeds": [], "true_seeds": []}
    for frame in frames:
        net.max_objects = max(1, len(frame.objects))
        rows["detector_seeds"].append(net.segment(frame.cube).compute.to_dict())
        seeds = Centres.from_bins(np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin]
                                            for o in frame.objects if o.n_voxels]).reshape(-1, 3))
        full = net.segment(frame.cube, centres=seeds).compute.to_dict()
        full["macs"]["detect"] = net.detector_macs()  # seeded pass skipped the detector: count what it costs
        full["macs"]["total"] = full["macs"]["detect"] + full["macs"]["segment"]
        rows["true_seeds"].append(full)
    out = {}
    for mode, computes in rows.items():
        out[mode] = {
            "seconds": {s: float(np.mean([c["seconds"][s] for c in computes])) for s in (*STEPS, "total")},
            "macs": {s: float(np.mean([c["macs"][s] for c in computes])) for s in ("detect", "segment", "total")},
            "roi_voxels": float(np.mean([c["roi_voxels"] for c in computes])),
            "visited_points": float(np.mean([c["visited_points"] for c in computes])),
        }
    out["params"] = net.params
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "end_to_end.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    # the machine may be shared: the load average is recorded beside the figures
    results = {"threads": args.threads, "load_average_before": os.getloadavg(), "runs": {}}
    print(f"{'preset':8} {'segmenter':9} {'seeds':9} {'roi':>7} {'det G':>6} {'seg G':>6} "
          + " ".join(f"{s[:7]:>8}" for s in (*STEPS, "total")) + "   (ms)")
    for preset in ("small", "carrada"):
        for segmenter in ("minkunet", "spvcnn"):
            r = run(preset, segmenter, args.frames)
            results["runs"][f"{preset}/{segmenter}"] = r
            for mode in ("detector_seeds", "true_seeds"):
                m = r[mode]
                print(f"{preset:8} {segmenter:9} {mode.split('_')[0]:9} {m['roi_voxels']:7.0f} "
                      f"{m['macs']['detect'] / 1e9:6.2f} {m['macs']['segment'] / 1e9:6.2f} "
                      + " ".join(f"{m['seconds'][s] * 1e3:8.1f}" for s in (*STEPS, "total")))
    results["load_average_after"] = os.getloadavg()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
