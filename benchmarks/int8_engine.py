"""The segmenter in int8 against float in the compiled sparse engine, side by side in one process (one thread): the
shipped ``small`` pair on fresh simulated frames, both precisions on every frame alternately (so the machine's load
hits both alike), after warm-up frames.

Per precision: median milliseconds of each EraseNet stage and end to end (wall clock), and the segmenter network
alone on each frame's ROI in this thread's CPU time (best of ``--repeats``: on a shared machine the CPU time of the
thread moves far less than the wall clock); the ratios int8 / float. Accuracy: RA and RD mIoU of both against the
frames' truth, the share of ROI voxels (labelled by either) given one label by both. The int8 segmenter is
calibrated on simulated frames of the preset at ``models.export.quantize``'s seed (not the timed frames). Written to
benchmarks/results/int8_engine.json with the CPU model and flags, the int8 kernels' path and the load average.
Never asserts a time.

    .venv/bin/python -m benchmarks.int8_engine [--frames 16] [--seed 52] [--repeats 3] [--preset small|carrada]

``--preset carrada`` runs the shipped ``carrada`` pair (checkpoints/carrada/) on ``carrada`` frames.
"""

from __future__ import annotations

import functools
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import SHIPPED_PAIRS, Table, int_options_main, print_load
from models.export.label_agreement import roi_label_agreement
from models.heap import freeze_loaded_heap
from models.quantized.calibration import segmenter_inputs
from models.runtime import Runtime, load_erasenet
from models.sparse import compiled, int8
from radar.metrics import confusion_matrix, mean_iou
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "int8_engine.json"
WARM_UP = 2
PRECISIONS = ("float", "int8")


def _cpu() -> dict:
    name = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                 if line.startswith("model name")), platform.processor())
    flags = compiled.cpu_flags().split()
    return {"model": name, "cores": os.cpu_count(), "avx512f": "avx512f" in flags,
            "avx512_vnni": "avx512_vnni" in flags, "avx_vnni": "avx_vnni" in flags, "avx2": "avx2" in flags,
            "int8_kernels": int8.path()}


def _network_cpu_ms(nets: dict, cube: np.ndarray, repeats: int) -> dict[str, float]:
    """Each precision's segmenter network on this frame's ROI: best thread CPU time of ``repeats`` runs (ms)."""
    inputs = segmenter_inputs(nets["float"], [cube])
    if not inputs:
        return {}
    x = inputs[0]
    best = {precision: float("inf") for precision in PRECISIONS}
    for repeat in range(repeats):
        for precision in (PRECISIONS if repeat % 2 == 0 else PRECISIONS[::-1]):
            started = time.thread_time()
            nets[precision]._fused(x)
            best[precision] = min(best[precision], time.thread_time() - started)
    return {precision: 1e3 * seconds for precision, seconds in best.items()}


def compare(frames: list, repeats: int, preset: str = "small") -> dict:
    nets = {precision: load_erasenet(*SHIPPED_PAIRS[preset], Runtime("torch", precision)) for precision in PRECISIONS}
    freeze_loaded_heap()
    num_classes = nets["float"].profile.num_classes
    stages: dict[str, list[dict]] = {precision: [] for precision in PRECISIONS}
    network: dict[str, list[float]] = {precision: [] for precision in PRECISIONS}
    confusion = {(p, view): np.zeros((num_classes, num_classes), np.int64) for p in PRECISIONS for view in ("ra", "rd")}
    labels: dict[str, list[np.ndarray]] = {precision: [] for precision in PRECISIONS}
    for k, frame in enumerate(frames):
        order = PRECISIONS if k % 2 == 0 else PRECISIONS[::-1]
        for precision in order:
            started = time.perf_counter()
            result = nets[precision].segment(frame.cube)
            elapsed = time.perf_counter() - started
            if k < WARM_UP:
                continue
            stages[precision].append({**result.compute.seconds_by_stage(), "end_to_end": elapsed})
            confusion[precision, "ra"] += confusion_matrix(frame.ra_mask(), result.ra_mask, num_classes)
            confusion[precision, "rd"] += confusion_matrix(frame.rd_mask(), result.rd_mask, num_classes)
            labels[precision].append(result.labels)
        if k >= WARM_UP:
            for precision, ms in _network_cpu_ms(nets, frame.log_power(), repeats).items():
                network[precision].append(ms)
    medians = {p: {stage: 1e3 * float(np.median([s[stage] for s in rows])) for stage in rows[0]}
               for p, rows in stages.items()}
    network_ms = {p: float(np.median(values)) for p, values in network.items()}
    miou = {p: {view: 100 * mean_iou(confusion[p, view]) for view in ("ra", "rd")} for p in PRECISIONS}
    return {
        "frames": len(frames) - WARM_UP, "ms_median_wall": medians, "segmenter_network_cpu_ms_median": network_ms,
        "int8_over_float": {"segment_stage_wall": medians["int8"]["segment"] / medians["float"]["segment"],
                            "end_to_end_wall": medians["int8"]["end_to_end"] / medians["float"]["end_to_end"],
                            "segmenter_network_cpu": network_ms["int8"] / network_ms["float"]},
        "miou": miou, "miou_int8_minus_float": {v: miou["int8"][v] - miou["float"][v] for v in ("ra", "rd")},
        "roi_label_agreement": roi_label_agreement(labels["float"], labels["int8"]),
    }


STAGES = Table((("stage (ms, wall median)", "<28"), ("float", "9.1f"), ("int8", "9.1f"), ("int8/float", "12.2f")),
               separator="")


def run(frames: int, seed: int, repeats: int, preset: str = "small") -> dict:
    """Both precisions over ``frames`` simulated frames of scene ``seed`` (after the warm-up frames)."""
    torch.set_num_threads(1)
    simulated = list(simulate_sequence(preset, frames + WARM_UP, seed=seed))
    load_before = os.getloadavg()
    figures = compare(simulated, repeats, preset)
    return {**figures, "preset": preset, "threads": 1, "seed": seed, "load_average_before": load_before,
            "load_average_after": os.getloadavg(), "cpu": _cpu(), "when": time.strftime("%Y-%m-%d %H:%M:%S")}


def report(result: dict) -> None:
    wall, cpu, ratio = result["ms_median_wall"], result["segmenter_network_cpu_ms_median"], result["int8_over_float"]
    print(STAGES.header())
    for stage in wall["float"]:
        print(STAGES.row(stage, wall["float"][stage], wall["int8"][stage],
                         wall["int8"][stage] / max(wall["float"][stage], 1e-9)))
    print(STAGES.row("segmenter network (CPU ms)", cpu["float"], cpu["int8"], ratio["segmenter_network_cpu"]))
    print(f"mIoU RA {result['miou']['float']['ra']:.2f} -> {result['miou']['int8']['ra']:.2f}, RD "
          f"{result['miou']['float']['rd']:.2f} -> {result['miou']['int8']['rd']:.2f}; ROI voxels labelled alike "
          f"{100 * result['roi_label_agreement']:.2f} %  ({result['frames']} frames)")
    print_load(result)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    preset = "small"
    if "--preset" in argv:  # the one option that is not a number
        at = argv.index("--preset")
        preset = argv[at + 1] if at + 1 < len(argv) else ""
        del argv[at:at + 2]
        if preset not in SHIPPED_PAIRS:
            raise SystemExit(f"--preset must be one of {', '.join(SHIPPED_PAIRS)} (a preset with a shipped pair), "
                             f"got {preset!r}")
    results = RESULTS if preset == "small" else RESULTS.with_name(f"int8_engine_{preset}.json")
    return int_options_main(results, functools.partial(run, preset=preset), __doc__, argv, report=report,
                            positive=("frames", "repeats"), frames=16, seed=52, repeats=3)


if __name__ == "__main__":
    raise SystemExit(main())
