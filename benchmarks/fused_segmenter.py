"""The segmenter's fused inference form against the eager model, side by side in one process (one thread): the
shipped ``small`` pair (and the slimmed pair), simulated frames, both forms on every frame alternately (so the
machine's load hits both alike), after warm-up frames.

Per form: median milliseconds per frame of each EraseNet stage and end to end, and the segment stage's share; the
ratios fused / eager; labels compared on every frame (they must be equal). Written to
benchmarks/results/fused_segmenter.json with the CPU model and flags and the load average. Never asserts a time.

    .venv/bin/python -m benchmarks.fused_segmenter [--frames 24] [--seed 41]
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import int_options_main, print_load
from models.erasenet.model import EraseNet
from models.heap import freeze_loaded_heap
from models.sparse import compiled
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "fused_segmenter.json"
PAIRS = {"shipped": ("checkpoints/detector.pt", "checkpoints/segmenter.pt"),
         "slimmed": ("checkpoints/detector-slimmed.pt", "checkpoints/segmenter-slimmed.pt")}
WARM_UP = 2


def _cpu() -> dict:
    name = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                 if line.startswith("model name")), platform.processor())
    flags = compiled.cpu_flags().split()
    return {"model": name, "avx512f": "avx512f" in flags, "avx512_vnni": "avx512_vnni" in flags,
            "avx2": "avx2" in flags}


def compare(pair: tuple[str, str], cubes: list[np.ndarray]) -> dict:
    """Both forms of one pair over the same cubes, alternating which runs first."""
    nets = {form: EraseNet.from_checkpoints(*(REPO / p for p in pair), fused_segmenter=form == "fused")
            for form in ("eager", "fused")}
    freeze_loaded_heap()
    seconds: dict[str, list[dict]] = {form: [] for form in nets}
    equal = 0
    for k, cube in enumerate(cubes):
        order = ("eager", "fused") if k % 2 == 0 else ("fused", "eager")
        results = {}
        for form in order:
            started = time.perf_counter()
            results[form] = nets[form].segment(cube)
            elapsed = time.perf_counter() - started
            if k >= WARM_UP:
                seconds[form].append({**results[form].compute.seconds_by_stage(), "end_to_end": elapsed})
        equal += int(np.array_equal(results["eager"].labels, results["fused"].labels))
        assert results["eager"].compute.segment_macs == results["fused"].compute.segment_macs
    medians = {form: {stage: 1e3 * float(np.median([s[stage] for s in rows])) for stage in rows[0]}
               for form, rows in seconds.items()}
    return {"frames": len(cubes) - WARM_UP, "labels_equal_frames": equal, "frames_compared": len(cubes),
            "ms_median": medians,
            "fused_over_eager": {stage: medians["fused"][stage] / medians["eager"][stage]
                                 for stage in ("segment", "end_to_end")}}


def run(frames: int, seed: int) -> dict:
    """Both pairs in both forms over ``frames`` simulated frames of scene ``seed`` (after the warm-up frames)."""
    torch.set_num_threads(1)
    cubes = [frame.cube for frame in simulate_sequence("small", frames + WARM_UP, seed=seed)]
    load_before = os.getloadavg()
    return {"pairs": {name: compare(pair, cubes) for name, pair in PAIRS.items()}, "threads": 1,
            "load_average_before": load_before, "load_average_after": os.getloadavg(), "cpu": _cpu(),
            "engine": compiled.get_kernels(), "when": time.strftime("%Y-%m-%d %H:%M:%S")}


def report(result: dict) -> None:
    for name, figures in result["pairs"].items():
        ms = figures["ms_median"]
        print(f"{name}: segment {ms['eager']['segment']:.1f} -> {ms['fused']['segment']:.1f} ms, end to end "
              f"{ms['eager']['end_to_end']:.1f} -> {ms['fused']['end_to_end']:.1f} ms "
              f"(x{figures['fused_over_eager']['end_to_end']:.2f}); labels equal on "
              f"{figures['labels_equal_frames']}/{figures['frames_compared']} frames")
    print_load(result)


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, report=report, frames=24, seed=41)


if __name__ == "__main__":
    raise SystemExit(main())
