"""Where one `small` frame's time goes with the shipped model: stages, the segmenter's parts, each sparse layer.

One process, one thread, simulated frames with objects (seed 5), after two warm-up frames:

- ``stages``: milliseconds per frame of each stage of :meth:`models.erasenet.model.EraseNet.segment`;
- ``segment_parts``: inside the segment stage, the compiled engine's convolution kernels, the kernel maps (every
  level in one compiled pass, ``build_pyramid``; any built one by one: index grids, neighbour tables, coarser voxel
  sets) and the rest (input features, 1x1 shortcuts, concatenations, argmax;
  with ``--eager``, also BatchNorm, ReLU, residual sums, module calls and hooks);
- ``layers``: every sparse convolution shape (kernel voxels, C_in, C_out) with its calls, milliseconds per frame and
  useful GMAC/s (present neighbour pairs x C_in x C_out over its time). Counting the pairs runs inside the segment
  stage; its time is measured and deducted from that stage (``pair_counting_ms_deducted``), so ``rest`` is the
  model's, not the profile's.
- ``widths`` (``--widths``): the compiled 3^3 kernel at 8-64 channels in and out on the last frame's own
  submanifold maps at strides 1 and 2, so a layer's rate can be read apart from its level (``kernel_widths``).

Prints a table and writes benchmarks/results/frame_profile.json with the CPU flags and load average. Never asserts.

    .venv/bin/python -m benchmarks.frame_profile [--frames 10]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

import models.sparse.tensor as sparse_tensor
from models.erasenet.model import EraseNet
from models.heap import freeze_loaded_heap
from models.sparse import compiled
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "frame_profile.json"


class _Clock:
    """Seconds spent in wrapped functions, by part; per-layer seconds and useful MACs of the kernels."""

    def __init__(self) -> None:
        self.parts: collections.Counter[str] = collections.Counter()
        self.counting = 0.0  # seconds spent counting each kernel's pairs: the profile's own cost, deducted
        self.layers: dict[tuple[str, int, int, int], list[float]] = collections.defaultdict(lambda: [0, 0.0, 0.0])

    def wrap(self, owner: object, name: str, part: str) -> None:
        original = getattr(owner, name)

        def timed(*args, **kwargs):
            started = time.perf_counter()
            result = original(*args, **kwargs)
            self.parts[part] += time.perf_counter() - started
            return result

        setattr(owner, name, timed)

    def wrap_kernel(self, name: str) -> None:
        original = getattr(compiled, name)

        def timed(src, neighbours, weight, *rest):
            started = time.perf_counter()
            out = original(src, neighbours, weight, *rest)
            seconds = time.perf_counter() - started
            missing = src.shape[0] if name.startswith("neighbour_conv") else rest[0]
            pairs = int((neighbours < missing).sum())
            self.counting += time.perf_counter() - started - seconds
            row = self.layers[(name, weight.shape[0], weight.shape[1], weight.shape[2])]
            row[0] += 1
            row[1] += seconds
            row[2] += pairs * weight.shape[1] * weight.shape[2]
            self.parts["conv kernels"] += seconds
            return out

        setattr(compiled, name, timed)


WIDTHS = (8, 16, 24, 32, 48, 64)


def submanifold_maps(model: EraseNet, log_power: np.ndarray) -> dict[int, torch.Tensor]:
    """The 3^3 submanifold neighbour tables one frame's fused segmenter runs, one per level, keyed by its voxels."""
    maps: dict[int, torch.Tensor] = {}
    original = compiled.neighbour_conv_fused

    def keep(src, neighbours, weight, *rest, **kwargs):
        if neighbours.shape[1] == 27 and neighbours.shape[0] == src.shape[0]:
            maps.setdefault(src.shape[0], neighbours.clone())
        return original(src, neighbours, weight, *rest, **kwargs)

    compiled.neighbour_conv_fused = keep
    try:
        model.segment(log_power, kind=InputKind.log_power)
    finally:
        compiled.neighbour_conv_fused = original
    return maps


def kernel_widths(maps: dict[int, torch.Tensor], levels: int = 2, repeats: int = 9) -> list[dict]:
    """The compiled 3^3 kernel at C_in = C_out = :data:`WIDTHS` on one frame's own submanifold maps of its ``levels``
    finest levels (full resolution first): how its rate depends on the width on one map."""
    rows = []
    generator = torch.Generator().manual_seed(0)
    for voxels in sorted(maps, reverse=True)[:levels]:
        neighbours = maps[voxels]
        pairs = int((neighbours < voxels).sum())
        for width in WIDTHS:
            src = torch.randn(voxels, width, generator=generator)
            weight = torch.randn(27, width, width, generator=generator) / width
            times = []
            for i in range(repeats + 2):
                started = time.perf_counter()
                compiled.neighbour_conv_fused(src, neighbours, weight)
                if i >= 2:  # two warm-up calls
                    times.append(time.perf_counter() - started)
            seconds = sorted(times)[len(times) // 2]
            rows.append({"voxels": voxels, "pairs_per_voxel": pairs / voxels, "channels": width,
                         "ms": 1e3 * seconds, "gmacs_per_s": pairs * width * width / seconds / 1e9,
                         "ns_per_pair": 1e9 * seconds / pairs})
    return rows


def main() -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="timed frames (after 2 warm-up frames)")
    parser.add_argument("--output", default=str(RESULTS))
    parser.add_argument("--eager", action="store_true", help="the eager segmenter instead of its fused form")
    parser.add_argument("--widths", action="store_true", help="also time the compiled 3^3 kernel at 8-64 channels "
                                                               "on the last frame's maps at strides 1 and 2")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = EraseNet.from_checkpoints(REPO / "checkpoints" / "detector.pt", REPO / "checkpoints" / "segmenter.pt",
                                      fused_segmenter=not args.eager)
    cubes = [frame.log_power() for frame in simulate_sequence("small", args.frames + 2, seed=5)]
    clock = _Clock()
    for kernel in ("neighbour_conv", "scatter_conv", "neighbour_conv_fused", "scatter_conv_fused"):
        clock.wrap_kernel(kernel)  # the eager model's kernels, and the fused form's (the default)
    for name in ("build_kernel_map", "VoxelIndex", "downsample_coords"):
        clock.wrap(sparse_tensor, name, f"kernel maps: {name}")
    clock.wrap(sparse_tensor.KernelMapCache, "build_pyramid", "kernel maps: build_pyramid")
    load_before = os.getloadavg()
    for cube in cubes[:2]:
        model.segment(cube, kind=InputKind.log_power)
    freeze_loaded_heap()  # as the service and the batch jobs do: no full garbage collection over torch and the model
    clock.parts.clear()
    clock.layers.clear()
    clock.counting = 0.0
    stages: collections.Counter[str] = collections.Counter()
    for cube in cubes[2:]:
        for stage, seconds in model.segment(cube, kind=InputKind.log_power).compute.seconds.items():
            stages[stage] += seconds
    n = args.frames
    per_frame = {stage: 1e3 * seconds / n for stage, seconds in stages.items()}
    per_frame["segment"] -= 1e3 * clock.counting / n  # the pair counting above ran inside the segment stage
    parts = {part: 1e3 * seconds / n for part, seconds in clock.parts.items()}
    parts["rest"] = per_frame["segment"] - sum(parts.values())
    layers = [{"kernel": name, "offsets": k, "c_in": c_in, "c_out": c_out, "calls_per_frame": calls / n,
               "ms_per_frame": 1e3 * seconds / n, "useful_gmacs_per_s": macs / seconds / 1e9 if seconds else 0.0}
              for (name, k, c_in, c_out), (calls, seconds, macs)
              in sorted(clock.layers.items(), key=lambda kv: -kv[1][1])]
    result = {"frames": n, "runtime": model.runtime, "segmenter": "eager" if args.eager else "fused",
              "ms_per_frame": per_frame, "segment_parts_ms": parts,
              "pair_counting_ms_deducted": 1e3 * clock.counting / n,
              "layers": layers, "cpu_flags": [f for f in compiled.cpu_flags().split() if f.startswith(("avx", "fma"))],
              "load_average_before": load_before, "load_average_after": os.getloadavg()}
    print("ms per frame: " + ", ".join(f"{k} {v:.1f}" for k, v in per_frame.items())
          + f" (total {sum(per_frame.values()):.1f})")
    print("segment stage: " + ", ".join(f"{k} {v:.1f}" for k, v in parts.items()))
    print(f"{'kernel':15s} {'K':>3s} {'C_in':>5s} {'C_out':>5s} {'calls':>6s} {'ms/frame':>9s} {'GMAC/s':>7s}")
    for row in layers:
        print(f"{row['kernel']:15s} {row['offsets']:3d} {row['c_in']:5d} {row['c_out']:5d} "
              f"{row['calls_per_frame']:6.1f} {row['ms_per_frame']:9.2f} {row['useful_gmacs_per_s']:7.1f}")
    if args.widths:
        result["widths"] = kernel_widths(submanifold_maps(model, cubes[-1]))
        for row in result["widths"]:
            print(f"{row['voxels']:6d} voxels, {row['pairs_per_voxel']:5.1f} pairs/voxel, {row['channels']:3d} -> "
                  f"{row['channels']:3d} channels: {row['ms']:6.2f} ms, {row['gmacs_per_s']:5.1f} GMAC/s, "
                  f"{row['ns_per_pair']:5.1f} ns per pair")
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(result, indent=1))
    print(f"written to {args.output}; load average {load_before} -> {result['load_average_after']}")
    return result


if __name__ == "__main__":
    main()
