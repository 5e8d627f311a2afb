"""Simulator throughput on one core, where the time goes, and how simulated RD views compare with
CARRADA's statistics. Prints a table and writes benchmarks/results/simulate.json.

    .venv/bin/python benchmarks/simulate.py [--frames-small 30 --frames-carrada 10 --frames-nxp 4]

Targets: a carrada frame with labels in <= 0.5 s, an nxp frame in <= 3 s, on one core.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"  # one core: set before numpy loads its BLAS

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from radar import transforms  # noqa: E402
from radar.simulate import simulate_sequence  # noqa: E402

CARRADA_RD_REFERENCE = {"mean_db": 58.0, "std_db": 4.0, "max_db": 119.0}  # docs/design.md section 3.1
TARGET_S = {"carrada": 0.5, "nxp": 3.0}


def bench_preset(name: str, n_frames: int, seed: int = 0) -> dict:
    timings: dict[str, float] = {}
    rd_stats = []
    objects = 0
    start = time.perf_counter()
    for frame in simulate_sequence(name, n_frames, seed=seed, timings=timings):
        objects += len(frame.objects)
        rd = transforms.rd_view(frame.cube)
        rd_stats.append((rd.mean(), rd.std(), rd.max()))
    total = time.perf_counter() - start
    sim_total = sum(timings.values())
    stats = np.array(rd_stats)
    return {
        "frames": n_frames,
        "seconds_per_frame": sim_total / n_frames,
        "frames_per_second": n_frames / sim_total,
        "wall_seconds_incl_rd_view": total,
        "share": {k: v / sim_total for k, v in timings.items()},
        "seconds_per_frame_by_stage": {k: v / n_frames for k, v in timings.items()},
        "objects_per_frame": objects / n_frames,
        "rd_view": {"mean_db": float(stats[:, 0].mean()), "std_db": float(stats[:, 1].mean()),
                    "max_db": float(stats[:, 2].max())},
        "target_seconds_per_frame": TARGET_S.get(name),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames-small", type=int, default=30)
    parser.add_argument("--frames-carrada", type=int, default=10)
    parser.add_argument("--frames-nxp", type=int, default=4)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "simulate.json"))
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    results = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores_used": 1,
                    "python": platform.python_version(), "numpy": np.__version__},
        "presets": {name: bench_preset(name, n) for name, n in
                    (("small", args.frames_small), ("carrada", args.frames_carrada), ("nxp", args.frames_nxp))},
        "carrada_rd_reference": CARRADA_RD_REFERENCE,
    }
    print(f"{'preset':8} {'s/frame':>8} {'fps':>6} {'synth':>6} {'fft':>6} {'labels':>6} {'objs':>5} "
          f"{'RD mean':>8} {'RD std':>7} {'RD max':>7} {'target':>7}")
    for name, r in results["presets"].items():
        share = r["share"]
        print(f"{name:8} {r['seconds_per_frame']:8.3f} {r['frames_per_second']:6.2f} {share['synthesis']:6.1%} "
              f"{share['fft']:6.1%} {share['labels']:6.1%} {r['objects_per_frame']:5.1f} "
              f"{r['rd_view']['mean_db']:8.1f} {r['rd_view']['std_db']:7.1f} {r['rd_view']['max_db']:7.1f} "
              f"{r['target_seconds_per_frame'] or '-':>7}")
    ref = CARRADA_RD_REFERENCE
    print(f"CARRADA RD view (reference): mean {ref['mean_db']} dB, std {ref['std_db']} dB, max {ref['max_db']} dB")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
