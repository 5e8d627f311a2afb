"""Simulator throughput on one core, where the time goes, and how simulated RD views compare with
CARRADA's statistics. Prints a table and writes benchmarks/results/simulate.json.

    .venv/bin/python -m benchmarks.simulate [--frames-small 30 --frames-carrada 10 --frames-nxp 4]

Targets: a carrada frame with labels in <= 0.5 s, an nxp frame in <= 3 s, on one core.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[var] = "1"  # one core: set before numpy loads its BLAS

import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.harness import Table, int_options_main  # noqa: E402
from radar import transforms  # noqa: E402
from radar.simulate import simulate_sequence  # noqa: E402

CARRADA_RD_REFERENCE = {"mean_db": 58.0, "std_db": 4.0, "max_db": 119.0}  # docs/design.md section 3.1
TARGET_S = {"carrada": 0.5, "nxp": 3.0}
RESULTS = Path(__file__).resolve().parent / "results" / "simulate.json"


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


SUMMARY = Table((("preset", "8"), ("s/frame", "8.3f"), ("fps", "6.2f"), ("synth", "6.1%"), ("fft", "6.1%"),
                 ("labels", "6.1%"), ("objs", "5.1f"), ("RD mean", "8.1f"), ("RD std", "7.1f"), ("RD max", "7.1f"),
                 ("target", ">7")))


def run(frames_small: int, frames_carrada: int, frames_nxp: int) -> dict:
    """Every preset's figures, on the first core this process may use."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    return {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores_used": 1,
                    "python": platform.python_version(), "numpy": np.__version__},
        "presets": {name: bench_preset(name, n) for name, n in
                    (("small", frames_small), ("carrada", frames_carrada), ("nxp", frames_nxp))},
        "carrada_rd_reference": CARRADA_RD_REFERENCE,
    }


def report(results: dict) -> None:
    print(SUMMARY.header())
    for name, r in results["presets"].items():
        share, rd = r["share"], r["rd_view"]
        print(SUMMARY.row(name, r["seconds_per_frame"], r["frames_per_second"], share["synthesis"], share["fft"],
                          share["labels"], r["objects_per_frame"], rd["mean_db"], rd["std_db"], rd["max_db"],
                          r["target_seconds_per_frame"] or "-"))
    ref = CARRADA_RD_REFERENCE
    print(f"CARRADA RD view (reference): mean {ref['mean_db']} dB, std {ref['std_db']} dB, max {ref['max_db']} dB")


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, report=report, frames_small=30, frames_carrada=10,
                            frames_nxp=4)


if __name__ == "__main__":
    raise SystemExit(main())
