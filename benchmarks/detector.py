"""Stage-1 centre detector: params and MACs of every "smaller" variant per preset, and CPU forward
latency (batch 1) of the chosen variant per preset. Prints a table and writes
benchmarks/results/detector.json.

    .venv/bin/python benchmarks/detector.py [--repeats 10] [--threads 2]

MACs are analytic (models.compute), the correct convention (= FlopCounterMode FLOPs / 2); the
detector has no transposed convs, so the paper's convention gives the same figures. Paper: 2.08 M
params, 0.49 GMACs at 256 x 256 (carrada), 1.46 GMACs at 424 x 512 (nxp).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from models.compute import count_macs
from models.detector.centre_detector import SMALLER_VARIANT, VARIANTS
from models.detector.inference import FrozenDetector
from models.registry import create_model
from radar.profiles import get_profile

PRESETS = ("small", "carrada", "nxp")
PAPER = {"params": 2.08e6, "macs": {"carrada": 0.49e9, "nxp": 1.46e9}}


def cost_table() -> dict:
    """``{preset: {variant: {params, macs, macs_without_doppler_conv, by_stage}}}``."""
    table: dict = {}
    for preset in PRESETS:
        n_range, n_angle, n_doppler = get_profile(preset).shape
        table[preset] = {}
        for variant in VARIANTS:
            model = create_model("centre_detector", preset=preset, variant=variant)
            report = count_macs(model, (1, n_doppler, n_range, n_angle))
            table[preset][variant] = {
                "params": report.params,
                "macs": report.macs,
                "macs_paper": report.macs_paper,
                "macs_without_doppler_conv": report.macs - report.by_stage["doppler_compress"],
                "by_stage": report.by_stage,
            }
    return table


def closest_to_paper(table: dict) -> str:
    """Variant with the smallest sum of relative errors against the paper at carrada."""

    def error(variant: str) -> float:
        row = table["carrada"][variant]
        return abs(row["params"] / PAPER["params"] - 1) + abs(row["macs"] / PAPER["macs"]["carrada"] - 1)

    return min(VARIANTS, key=error)


def latency(preset: str, variant: str, repeats: int, warmup: int = 2) -> dict:
    """Forward seconds per frame (batch 1, eval, no grad) of one detector on random input."""
    n_range, n_angle, n_doppler = get_profile(preset).shape
    torch.manual_seed(0)
    model = create_model("centre_detector", preset=preset, variant=variant).eval()
    log_power = torch.randn(1, n_doppler, n_range, n_angle)
    times = []
    with torch.inference_mode():
        for i in range(warmup + repeats):
            start = time.perf_counter()
            model(log_power)
            if i >= warmup:
                times.append(time.perf_counter() - start)
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": repeats}


def inference_forms(preset: str, repeats: int) -> dict:
    """Forward ms of the chosen variant in each inference form, interleaved in one loop (ratios are what
    count on a shared machine): eager, channels_last, and FrozenDetector (BN folded, channels_last, traced)."""
    n_range, n_angle, n_doppler = get_profile(preset).shape
    torch.manual_seed(0)
    model = create_model("centre_detector", preset=preset, variant=SMALLER_VARIANT).eval()
    log_power = torch.randn(1, n_doppler, n_range, n_angle)
    channels_last = copy.deepcopy(model).to(memory_format=torch.channels_last)
    forms = {"eager": (model, log_power),
             "channels_last": (channels_last, log_power.contiguous(memory_format=torch.channels_last)),
             "folded_channels_last_traced": (FrozenDetector(model, tuple(log_power.shape)), log_power)}
    times: dict[str, list[float]] = {name: [] for name in forms}
    with torch.inference_mode():
        reference = model(log_power)["heatmap"]
        max_diff = {name: float((m(x)["heatmap"] - reference).abs().max()) for name, (m, x) in forms.items()}
        for _ in range(repeats):
            for name, (m, x) in forms.items():
                start = time.perf_counter()
                m(x)
                times[name].append(time.perf_counter() - start)
    return {name: {"median_s": statistics.median(t), "min_s": min(t), "max_abs_diff_heatmap": max_diff[name]}
            for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "detector.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    table = cost_table()
    closest = closest_to_paper(table)
    timings = {preset: latency(preset, SMALLER_VARIANT, args.repeats) for preset in PRESETS}
    load_forms = os.getloadavg()
    forms = {preset: inference_forms(preset, args.repeats) for preset in ("small", "carrada")}
    results = {
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "torch_threads": args.threads,
            "load_average_1min": os.getloadavg()[0],
            "python": platform.python_version(),
            "torch": torch.__version__,
        },
        "macs_convention": "correct (FlopCounterMode FLOPs / 2); batch 1",
        "paper": PAPER,
        "chosen_variant": SMALLER_VARIANT,
        "closest_to_paper_at_carrada": closest,
        "variants": {name: v.description for name, v in VARIANTS.items()},
        "cost": table,
        "latency_chosen_variant": timings,
        "inference_forms": {"load_average_before": load_forms, "load_average_after": os.getloadavg(), **forms},
    }

    print(f"{'preset':8} {'variant':12} {'params M':>9} {'GMACs':>7} {'GMACs w/o D-conv':>17}")
    for preset, rows in table.items():
        for variant, row in rows.items():
            mark = " *" if variant == SMALLER_VARIANT else ""
            print(
                f"{preset:8} {variant:12} {row['params'] / 1e6:9.3f} {row['macs'] / 1e9:7.3f} "
                f"{row['macs_without_doppler_conv'] / 1e9:17.3f}{mark}"
            )
    print(f"paper: 2.08 M params, 0.49 GMACs (carrada), 1.46 GMACs (nxp); closest at carrada: {closest}")
    print(f"forward latency of {SMALLER_VARIANT!r}, batch 1, {args.threads} thread(s):")
    for preset, timing in timings.items():
        print(f"  {preset:8} median {timing['median_s'] * 1e3:7.1f} ms   min {timing['min_s'] * 1e3:7.1f} ms")
    print(f"inference forms of {SMALLER_VARIANT!r} (interleaved; median / min ms), load {load_forms[0]:.2f}:")
    for preset, rows in forms.items():
        print(f"  {preset:8} " + "   ".join(f"{name} {row['median_s'] * 1e3:.1f} / {row['min_s'] * 1e3:.1f}"
                                          for name, row in rows.items()))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
