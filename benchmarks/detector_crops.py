"""The detector's training step at a paper-size radar: whole frames against range x angle windows (crop
training, ``radarseg train detector --crop R A``), and the CPU speed-ups tried on the window step, side by side in
one process.

One step = forward, the centre losses, backward and an Adam update on a batch of normalised log power with targets
from random centres (the step's cost does not depend on the values). Variants are run round-robin, ``--rounds``
times each, so every one sees the same machine load; the figure is the median thread CPU seconds of a step (and
wall seconds), with each variant's ratio to the whole-frame step. Writes benchmarks/results/detector_crops.json;
never asserts a time.

    .venv/bin/python -m benchmarks.detector_crops [--preset carrada] [--crop 64 128] [--batch-size 8]
        [--rounds 3] [--steps 3] [--threads 1] [--variants whole,crop,crop_channels_last,crop_bf16]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import machine, write_with_load
from models.detector.targets import build_centre_targets, crop_centre_targets
from models.registry import create_model
from pipelines.training.config import RECIPES
from pipelines.training.windows import WindowSampler
from radar.profiles import get_profile

RESULTS = Path(__file__).parent / "results" / "detector_crops.json"
VARIANTS = ("whole", "crop", "crop_channels_last", "crop_bf16", "crop_compile")


def _batch(profile, batch_size: int, crop: tuple[int, int] | None, rng: np.random.Generator) -> dict:
    """A batch as the detector task collates it: input (B, D, h, w), targets cut to the windows."""
    n_range, n_angle, n_doppler = profile.shape
    centres = [np.column_stack([rng.uniform(0, n_range - 1, 3), rng.uniform(0, n_angle - 1, 3),
                                rng.uniform(0, n_doppler - 1, 3)]) for _ in range(batch_size)]
    targets = build_centre_targets(centres, (n_range, n_angle))
    if crop is None:
        return {"input": torch.randn(batch_size, n_doppler, n_range, n_angle), "targets": targets}
    sampler = WindowSampler(crop, (n_range, n_angle))
    windows = [sampler.draw(c, rng) for c in centres]
    origins = torch.tensor([[w.range_start, w.angle_start] for w in windows])
    return {"input": torch.randn(batch_size, n_doppler, *crop), "window_origins": origins,
            "targets": crop_centre_targets(targets, (origins // sampler.stride).tolist(), sampler.cells)}


def _step_function(variant: str, preset: str, batch: dict) -> Callable[[], None]:
    config = RECIPES["detector"]["crops"].model_config
    model = create_model("centre_detector", preset=preset, **config).train()
    inputs = batch["input"]
    if variant == "crop_channels_last":
        model = model.to(memory_format=torch.channels_last)
        inputs = inputs.contiguous(memory_format=torch.channels_last)
    forward = torch.compile(model) if variant == "crop_compile" else model
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    extra = {"window_origins": batch["window_origins"]} if "window_origins" in batch else {}

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=variant == "crop_bf16"):
            outputs = forward(inputs, **extra)
        losses = model.compute_loss({k: v.float() for k, v in outputs.items()}, batch["targets"])
        losses["total"].backward()
        optimizer.step()

    return step


def run(*, preset: str, crop: tuple[int, int], batch_size: int, rounds: int, steps: int, threads: int,
        variants: tuple[str, ...]) -> dict:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    profile = get_profile(preset)
    load_before = os.getloadavg()
    steps_of = {}
    for variant in variants:
        batch = _batch(profile, batch_size, None if variant == "whole" else crop, rng)
        step = _step_function(variant, preset, batch)
        started = time.perf_counter()
        step()  # warm-up (and compilation)
        steps_of[variant] = (step, time.perf_counter() - started)
    cpu = {v: [] for v in variants}
    wall = {v: [] for v in variants}
    for _ in range(rounds):
        for variant in variants:
            step = steps_of[variant][0]
            for _ in range(steps):
                cpu_start, wall_start = time.thread_time(), time.perf_counter()
                step()
                cpu[variant].append(time.thread_time() - cpu_start)
                wall[variant].append(time.perf_counter() - wall_start)
    rows = {}
    for variant in variants:
        rows[variant] = {"cpu_s_per_step": statistics.median(cpu[variant]),
                         "wall_s_per_step": statistics.median(wall[variant]),
                         "first_step_s": steps_of[variant][1], "steps": len(cpu[variant])}
    base = rows.get("whole")
    for variant, row in rows.items():
        if base:
            row["cheaper_than_whole"] = base["cpu_s_per_step"] / row["cpu_s_per_step"]
        if variant != "crop" and "crop" in rows:
            row["speedup_over_crop"] = rows["crop"]["cpu_s_per_step"] / row["cpu_s_per_step"]
    return {"preset": preset, "crop": list(crop), "batch_size": batch_size, "threads": threads, "rounds": rounds,
            "model_config": RECIPES["detector"]["crops"].model_config, "rows": rows, "machine": machine(),
            "torch": torch.__version__, "load_average_before": load_before}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="carrada")
    parser.add_argument("--crop", type=int, nargs=2, default=list(RECIPES["detector"]["crops"].crop))
    parser.add_argument("--batch-size", type=int, default=RECIPES["detector"]["crops"].batch_size)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=3, help="steps of each variant per round")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--variants", default="whole,crop,crop_channels_last,crop_bf16",
                        help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    variants = tuple(v for v in args.variants.split(",") if v)
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown or min(args.rounds, args.steps, args.threads, args.batch_size) < 1:
        parser.error(f"variants must be of {VARIANTS} (got {unknown}); rounds, steps, threads, batch size >= 1")
    result = run(preset=args.preset, crop=tuple(args.crop), batch_size=args.batch_size, rounds=args.rounds,
                 steps=args.steps, threads=args.threads, variants=variants)
    for variant, row in result["rows"].items():
        ratio = f", {row['cheaper_than_whole']:.2f}x cheaper than whole frames" if "cheaper_than_whole" in row else ""
        print(f"{variant:20s} {row['cpu_s_per_step']:.3f} CPU s/step ({row['wall_s_per_step']:.3f} s wall){ratio}")
    print(f"{result['preset']}, batch {result['batch_size']}, {result['threads']} thread(s), "
          f"flags {' '.join(result['machine']['flags'])}, load {result['load_average_before'][0]:.2f}")
    write_with_load(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
