"""The 2-D baselines (U-Net per view, TMVA-Net, SMVA-Net): params, MACs by both counters per preset,
and CPU forward latency (batch 1). Prints a table and writes benchmarks/results/baselines.json.

    .venv/bin/python benchmarks/baselines.py [--repeats 3] [--threads 2] [--latency-presets small carrada]

MACs are analytic (models.compute): ``macs`` is the correct count (= FlopCounterMode FLOPs / 2);
``macs_paper`` counts transposed convs per output position, as the paper's counter did (overcounts a
2x2 stride-2 transposed conv by 4, a (2, 1) one by 2). Reference (docs/design.md sections 9 and 12): TMVA-Net
5,630,984 params, 95.62 G correct / 102.35 G paper; SMVA-Net 4,739,336, 65.72 / 72.35; U-Net 31.04 M,
paper table 54.84 G and 13.71 G at carrada (its 256 x 256 view is RA, the 256 x 64 one RD).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import torch

from benchmarks.timing import time_call
from models.compute import count_macs
from models.registry import create_model
from radar.profiles import get_profile

PRESETS = ("small", "carrada", "nxp")
PAPER = {"tmvanet": {"params": 5_630_984, "macs": 95.62e9, "macs_paper": 102.35e9},
         "smvanet": {"params": 4_739_336, "macs": 65.72e9, "macs_paper": 72.35e9},
         "unet_ra": {"params": 31.04e6, "macs_paper": 54.84e9}, "unet_rd": {"params": 31.04e6, "macs_paper": 13.71e9}}
MODELS = {"tmvanet": ("tmvanet", {}), "smvanet": ("smvanet", {}), "unet_ra": ("unet", {"view": "ra"}),
          "unet_rd": ("unet", {"view": "rd"})}


def input_shapes(model: torch.nn.Module, preset: str) -> list[tuple[int, ...]]:
    """Batch-1 input shapes of a baseline at a preset."""
    r, a, d = get_profile(preset).shape
    view = getattr(model, "view", None)
    if view is not None:
        return [(1, 1, r, a if view == "ra" else d)]
    t = model.n_frames
    return [(1, t, r, d), (1, t, r, a), (1, t, a, d)]


def cost_table() -> dict:
    table: dict = {}
    for preset in PRESETS:
        table[preset] = {}
        for key, (name, config) in MODELS.items():
            model = create_model(name, preset=preset, **config)
            report = count_macs(model, *input_shapes(model, preset))
            table[preset][key] = {"params": report.params, "macs": report.macs, "macs_paper": report.macs_paper,
                                  "input_shapes": [list(s) for s in report.input_shapes]}
    return table


@torch.no_grad()
def latency(key: str, preset: str, repeats: int) -> dict:
    name, config = MODELS[key]
    model = create_model(name, preset=preset, **config).eval()
    inputs = [torch.randn(shape) for shape in input_shapes(model, preset)]
    return time_call(lambda: model(*inputs), repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--latency-presets", nargs="*", default=["small", "carrada"], choices=PRESETS)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "baselines.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    costs = cost_table()
    print(f"{'preset':8} {'model':8} {'params':>11} {'GMACs':>8} {'GMACs (paper)':>14}")
    for preset, rows in costs.items():
        for key, row in rows.items():
            print(f"{preset:8} {key:8} {row['params']:>11,} {row['macs'] / 1e9:>8.2f} {row['macs_paper'] / 1e9:>14.2f}")
    latencies: dict = {}
    for preset in args.latency_presets:
        latencies[preset] = {}
        for key in MODELS:
            latencies[preset][key] = latency(key, preset, args.repeats)
            print(f"latency {preset:8} {key:8} {latencies[preset][key]['median_s'] * 1e3:9.1f} ms (median)")
    result = {
        "costs": costs,
        "reference": PAPER,
        "macs_conventions": {"macs": "correct (FlopCounterMode FLOPs / 2)",
                             "macs_paper": "transposed convs counted per output position (paper/thop)"},
        "latency_batch1": latencies,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "threads": args.threads,
                    "torch": torch.__version__, "note": "shared 2-core CPU under load from other jobs"},
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
