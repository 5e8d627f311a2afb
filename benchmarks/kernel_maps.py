"""A frame's kernel maps: every level in one compiled pass (`KernelMapCache.build_pyramid`) against one by one.

The shipped pair segments simulated `small` frames (seed 5) once, keeping each frame's ROI voxels; then, one thread,
interleaved and repeated, the segmenter's maps are built both ways on those voxels: the 3^3 submanifold map of
strides 1..16 and the 2^3 down-sampling maps between them, with the coordinates of every stride. The tables are
checked equal before any timing. Prints milliseconds per frame and the ratio, writes
benchmarks/results/kernel_maps.json with the CPU flags and the load average. Never asserts a speed.

    .venv/bin/python -m benchmarks.kernel_maps [--frames 12] [--repeats 9]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from benchmarks.sparse_conv import machine_info
from models.erasenet.model import EraseNet
from models.segmenter import fused
from models.sparse.tensor import KernelMapCache
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "kernel_maps.json"
LEVELS = 5  # the shipped MinkUNet: strides 1, 2, 4, 8, 16


def frame_rois(frames: int) -> list[torch.Tensor]:
    """The ROI voxels (N, 4) the shipped pair's segmenter receives on `frames` simulated frames."""
    captured: list[torch.Tensor] = []
    original = fused.FusedMinkUNet.__call__

    def capture(self, x):
        captured.append(x.coords.clone())
        return original(self, x)

    model = EraseNet.from_checkpoints(REPO / "checkpoints" / "detector.pt", REPO / "checkpoints" / "segmenter.pt")
    fused.FusedMinkUNet.__call__ = capture
    try:
        for frame in simulate_sequence("small", frames, seed=5):
            model.segment(frame.log_power(), kind=InputKind.log_power)
    finally:
        fused.FusedMinkUNet.__call__ = original
    return captured


def one_by_one(coords: torch.Tensor) -> KernelMapCache:
    cache = KernelMapCache(coords, 1)
    for level in range(LEVELS):
        cache.kernel_map(1 << level, 3, 1)
        if level + 1 < LEVELS:
            cache.kernel_map(1 << level, 2, 2)
    return cache


def one_pass(coords: torch.Tensor) -> KernelMapCache:
    cache = KernelMapCache(coords, 1)
    if not cache.build_pyramid(1, LEVELS):
        raise RuntimeError("build_pyramid declined a ROI (not sorted, or the compiled engine is off)")
    return cache


def check_equal(rois: list[torch.Tensor]) -> None:
    for coords in rois:
        expected, built = one_by_one(coords), one_pass(coords)
        for key, reference in expected._maps.items():
            if not torch.equal(built._maps[key].neighbours, reference.neighbours):
                raise AssertionError(f"the one-pass map {key} differs from the one built alone")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rois = frame_rois(args.frames)
    check_equal(rois)
    load_before = os.getloadavg()
    seconds: dict[str, list[float]] = {"one_by_one": [], "one_pass": []}
    for repeat in range(args.repeats):
        ways = (("one_by_one", one_by_one), ("one_pass", one_pass))
        for name, build in ways if repeat % 2 == 0 else ways[::-1]:
            started = time.perf_counter()
            for coords in rois:
                build(coords)
            seconds[name].append((time.perf_counter() - started) / len(rois))
    ms = {name: 1e3 * statistics.median(values) for name, values in seconds.items()}
    result = {"frames": len(rois), "roi_voxels_mean": sum(len(c) for c in rois) / len(rois), "levels": LEVELS,
              "repeats": args.repeats, "ms_per_frame_median": ms,
              "one_pass_speed_up": ms["one_by_one"] / ms["one_pass"],
              "machine": machine_info(), "load_average_before": load_before, "load_average_after": os.getloadavg(),
              "when": time.strftime("%Y-%m-%d %H:%M:%S")}
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(result, indent=1))
    print(f"kernel maps per frame ({result['roi_voxels_mean']:.0f} ROI voxels, {LEVELS} strides): one by one "
          f"{ms['one_by_one']:.2f} ms, one pass {ms['one_pass']:.2f} ms (x{result['one_pass_speed_up']:.1f}); "
          f"load average {load_before} -> {result['load_average_after']}; {result['machine']['simd_flags']}")
    return result


if __name__ == "__main__":
    main()
