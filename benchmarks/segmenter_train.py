"""Segmenter training steps per second on real ROIs: simulated frames, regions grown from jittered true
centres (as `pipelines.training.train`'s ROI dataset does), MinkUNet at the shipped ratio (0.25) and the paper's (0.37).

One step = forward, weighted cross-entropy, backward and an SGD (Nesterov) update on a batch of ROIs, kernel
maps built inside the step as in training. Batches are prepared before timing, so only the model's work is
measured. Prints the figures and merges them under ``--label`` into benchmarks/results/segmenter_train.json
(one label per code version, e.g. ``before`` and ``after``); never asserts a time.

    .venv/bin/python -m benchmarks.segmenter_train --label after [--frames 8] [--batch-size 2] [--repeats 3]
        [--kernels auto|compiled|reference] [--smoke]
    .venv/bin/python -m benchmarks.segmenter_train --against 18f7d7f --rounds 3   # before/after, interleaved

``--against REF`` exports that commit's tree (``git archive``) to a temporary folder and runs this benchmark
there and here in alternating processes, ``--rounds`` times each, so both versions see the same machine
load: here once per sparse kernels setting (``after``: the compiled one, ``after_torch``: the pure-PyTorch one); it
records all and the ratios of their median step times under the label ``REF..HEAD``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.registry import create_model
from models.sparse import SparseTensor, compiled
from pipelines.training.config import DEFAULT_JITTER_STD
from radar.region_growing import grow_regions
from radar.roi import roi_points
from radar.simulate import simulate_sequence

RESULTS = Path(__file__).parent / "results" / "segmenter_train.json"
JITTER_STD_BINS = DEFAULT_JITTER_STD  # pipelines.training.train's default seed errors (range, angle, Doppler bins)


@dataclass(frozen=True)
class BenchConfig:
    preset: str = "small"
    frames: int = 8
    batch_size: int = 2
    repeats: int = 3
    ratios: tuple[float, ...] = (0.25, 0.37)
    threads: int = 1
    seed: int = 0
    kernels: str = "auto"  # the sparse kernels (models.sparse.compiled): auto, compiled or reference


def roi_samples(preset: str, n_frames: int, seed: int) -> list[dict[str, torch.Tensor]]:
    """ROI samples of simulated frames with at least one object: coords (N, 3), features (N, 4), labels (N,)."""
    frames = [f for f in simulate_sequence(preset, n_frames, seed=seed + 5) if f.objects]
    first = frames[0].log_power()
    mean_db, std_db = float(first.mean()), float(first.std())
    rng = np.random.default_rng(seed)
    samples = []
    for frame in frames:
        log_power = frame.log_power()
        seeds = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects], float)
        seeds = np.clip(seeds + rng.normal(size=seeds.shape) * JITTER_STD_BINS, 0, np.asarray(log_power.shape) - 1)
        regions = grow_regions(log_power, seeds, frame.profile)
        voxels = regions.voxels if len(regions) else regions.seeds
        points = roi_points(voxels, log_power, frame.profile, mean_db=mean_db, std_db=std_db)
        samples.append({"coords": torch.from_numpy(points.coords), "features": torch.from_numpy(points.features),
                        "labels": torch.from_numpy(frame.labels[tuple(voxels.T)].astype(np.int64))})
    return samples


def collate(samples: list[dict[str, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(coords (N, 4) with the sample index first, features (N, 4), labels (N,))."""
    coords = torch.cat([torch.cat([torch.full((len(s["coords"]), 1), b, dtype=torch.int64), s["coords"]], dim=1)
                        for b, s in enumerate(samples)])
    return coords, torch.cat([s["features"] for s in samples]), torch.cat([s["labels"] for s in samples])


def bench_ratio(ratio: float, batches: list, cfg: BenchConfig) -> dict:
    torch.manual_seed(cfg.seed)
    model = create_model("minkunet", preset=cfg.preset, ratio=ratio).train()
    optimizer = torch.optim.SGD(model.parameters(), lr=0.05, momentum=0.9, weight_decay=1e-4, nesterov=True)
    num_classes = model.config["num_classes"]
    weights = torch.ones(num_classes)

    def step(coords, feats, labels) -> None:
        optimizer.zero_grad(set_to_none=True)
        loss = nn.functional.cross_entropy(model(SparseTensor(coords, feats)), labels, weight=weights)
        loss.backward()
        optimizer.step()

    step(*batches[0])  # warm-up
    times = []
    for _ in range(cfg.repeats):
        for batch in batches:
            start = time.perf_counter()
            step(*batch)
            times.append(time.perf_counter() - start)
    median = statistics.median(times)
    return {"ratio": ratio, "widths": model.config["widths"], "median_step_s": median, "min_step_s": min(times),
            "steps_per_s": 1.0 / median, "steps": len(times)}


def main(cfg: BenchConfig, label: str, output: Path) -> dict:
    torch.set_num_threads(cfg.threads)
    compiled.set_kernels(cfg.kernels)
    kernels = "compiled" if cfg.kernels != "reference" and compiled.available() else "reference"
    samples = roi_samples(cfg.preset, cfg.frames, cfg.seed)
    batches = [collate(samples[i:i + cfg.batch_size]) for i in range(0, len(samples) - cfg.batch_size + 1,
                                                                       cfg.batch_size)]
    load_before = os.getloadavg()
    rows = [bench_ratio(ratio, batches, cfg) for ratio in cfg.ratios]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    result = {
        "config": asdict(cfg), "commit": commit, "rows": rows, "kernels": kernels,
        "voxels_per_batch_mean": float(np.mean([len(b[0]) for b in batches])),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "load_average_before": load_before, "load_average_after": os.getloadavg()},
    }
    print(f"{label}: {kernels} kernels, {cfg.preset}, batches of {cfg.batch_size} ROIs, "
          f"{result['voxels_per_batch_mean']:.0f} voxels per batch, {cfg.threads} thread(s), "
          f"load {load_before[0]:.2f} -> {os.getloadavg()[0]:.2f}")
    for row in rows:
        print(f"  MinkUNet ratio {row['ratio']}: {row['median_step_s'] * 1e3:7.1f} ms/step median "
              f"({row['min_step_s'] * 1e3:.1f} min), {row['steps_per_s']:.2f} steps/s")
    merged = json.loads(output.read_text()) if output.is_file() else {}
    merged[label] = result
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(merged, indent=2) + "\n")
    return result


def against(ref: str, rounds: int, cfg: BenchConfig, output: Path) -> dict:
    """Interleaved before (commit `ref`) / after (this tree) runs in separate processes; see the docstring."""
    repo = Path(__file__).resolve().parents[1]
    args = ["-m", "benchmarks.segmenter_train", "--preset", cfg.preset, "--frames", str(cfg.frames),
            "--batch-size", str(cfg.batch_size), "--repeats", str(cfg.repeats), "--threads", str(cfg.threads)]
    steps: dict[str, dict[float, list[float]]] = {"before": {}, "after": {}, "after_torch": {}}
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", ref], cwd=repo, capture_output=True, check=True).stdout
        old_tree = Path(tmp) / "tree"
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(old_tree, filter="data")
        versions = (("before", old_tree, []), ("after", repo, ["--kernels", "compiled"]),
                    ("after_torch", repo, ["--kernels", "reference"]))
        for _ in range(rounds):
            for label, tree, extra in versions:
                out = Path(tmp) / f"{label}.json"
                subprocess.run([sys.executable, *args, *extra, "--label", label, "--output", str(out)], cwd=tree,
                               check=True, env={**os.environ, "PYTHONPATH": str(tree)}, stdout=subprocess.DEVNULL)
                for row in json.loads(out.read_text())[label]["rows"]:
                    steps[label].setdefault(row["ratio"], []).append(row["median_step_s"])
    rows = []
    for ratio in steps["after"]:
        before, after = statistics.median(steps["before"][ratio]), statistics.median(steps["after"][ratio])
        after_torch = statistics.median(steps["after_torch"][ratio])
        rows.append({"ratio": ratio, "before_step_s": before, "after_step_s": after, "speedup": before / after,
                     "after_torch_step_s": after_torch, "torch_engine_speedup": before / after_torch,
                     "before_runs": steps["before"][ratio], "after_runs": steps["after"][ratio],
                     "after_torch_runs": steps["after_torch"][ratio]})
        print(f"MinkUNet ratio {ratio}: before {before * 1e3:.0f} ms/step ({1 / before:.2f} steps/s), after "
              f"{after * 1e3:.0f} ms/step ({1 / after:.2f} steps/s): {before / after:.2f}x; after on the torch "
              f"engine {after_torch * 1e3:.0f} ms/step: {before / after_torch:.2f}x")
    result = {"config": asdict(cfg), "ref": ref, "rounds": rounds, "rows": rows,
              "machine": {"cpu_flags": [f for f in compiled.cpu_flags().split()
                                        if f.startswith(("avx", "fma", "sse4"))],
                          "load_average_before": load_before, "load_average_after": os.getloadavg()}}
    merged = json.loads(output.read_text()) if output.is_file() else {}
    merged[f"{ref}..HEAD"] = result
    output.write_text(json.dumps(merged, indent=2) + "\n")
    return result


def parse_args(argv: list[str] | None = None) -> tuple[BenchConfig, str, Path, str | None, int]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", default="after", help="key of this run in the results file")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--kernels", default="auto", choices=compiled.KERNELS, help="sparse kernels (default auto)")
    parser.add_argument("--smoke", action="store_true", help="two frames, one repeat, the shipped ratio only")
    parser.add_argument("--output", default=str(RESULTS))
    parser.add_argument("--against", help="git commit to compare with, interleaved (see the docstring)")
    parser.add_argument("--rounds", type=int, default=3, help="with --against: runs of each version")
    args = parser.parse_args(argv)
    if args.smoke:
        cfg = BenchConfig(preset=args.preset, frames=2, batch_size=1, repeats=1, ratios=(0.25,), threads=args.threads,
                          kernels=args.kernels)
    else:
        cfg = BenchConfig(preset=args.preset, frames=args.frames, batch_size=args.batch_size, repeats=args.repeats,
                          threads=args.threads, kernels=args.kernels)
    return cfg, args.label, Path(args.output), args.against, args.rounds


if __name__ == "__main__":
    config, label, output_path, ref, n_rounds = parse_args()
    if ref:
        against(ref, n_rounds, config, output_path)
    else:
        main(config, label, output_path)
