"""ERASE-Net against the 2-D baselines in one run on one machine: CPU latency per frame and MACs side by
side, as ratios to ERASE-Net. Prints a table and writes benchmarks/results/compare.json.

    .venv/bin/python -m benchmarks.compare [--preset small|carrada] [--frames 8] [--repeats 3] [--threads 1]

ERASE-Net runs end to end (:meth:`models.erasenet.model.EraseNet.segment` on a simulated frame's log-power cube:
normalisation, detector, decoding, region growing, sparse segmenter, projections). It is the preset's shipped pair
(:data:`benchmarks.harness.SHIPPED_PAIRS`: checkpoints/detector.pt + segmenter.pt at ``small``, checkpoints/carrada/
at ``carrada``); with ``--random-weights`` (asked for, never a fallback) the small pair's
architectures with random weights and the detector's top-K seeds (K = true objects, threshold 0, as
benchmarks/end_to_end.py). Its MACs are the mean per frame of
detector + segmenter (the segmenter's depend on the ROI). The baselines (U-Net RD and RA, TMVA-Net,
SMVA-Net) run one forward pass at batch 1 with random weights and inputs (their cost does not depend on
either; :mod:`benchmarks.baselines`), their MACs analytic by both counters (correct, and the paper's,
which counts a transposed conv per output position). Every dense network gets the same dense-side
optimisations as ERASE-Net's detector (:class:`models.detector.inference.FrozenDetector`: BatchNorms folded,
channels_last, traced), so the ratios stay fair; each baseline's eager time is reported beside it.
Latency: median over ``--repeats`` x ``--frames`` runs (baselines: ``--repeats``), after a warm-up; GMAC/s
is the row's correct MACs over its median time. Figures are for comparing within one run only.
ERASE-Net runs on both sparse engines, interleaved frame by frame (:mod:`models.sparse.compiled`): its row is
the compiled engine's, the ratios are to it, and a second row gives the pure-PyTorch engine's time.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from benchmarks.baselines import MODELS, input_shapes, latency
from benchmarks.harness import SHIPPED_PAIRS
from benchmarks.timing import time_call
from models.checkpoint import load_checkpoint
from models.compute import count_macs
from models.detector.inference import fold_batch_norms
from models.erasenet.model import EraseNet
from models.registry import create_model
from models.sparse import compiled
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[1]
CHECKPOINTS = REPO / "checkpoints"
ROWS = {"unet_rd": "U-Net RD", "unet_ra": "U-Net RA", "tmvanet": "TMVA-Net", "smvanet": "SMVA-Net"}


def build_erasenet(preset: str, first_log_power: np.ndarray, *, random_weights: bool = False) -> EraseNet:
    """The preset's shipped pair; with ``random_weights``, the small pair's architectures built for ``preset``
    with random weights (its seeds then the top-K detector peaks, threshold 0)."""
    if not random_weights:
        detector_path, segmenter_path = SHIPPED_PAIRS[preset]
        return EraseNet.from_checkpoints(load_checkpoint(detector_path), load_checkpoint(segmenter_path))
    det, seg = load_checkpoint(CHECKPOINTS / "detector.pt"), load_checkpoint(CHECKPOINTS / "segmenter.pt")
    torch.manual_seed(0)
    detector = create_model(det.model_name, **{**det.config, "preset": preset})
    segmenter = create_model(seg.model_name, **{**seg.config, "preset": preset})
    return EraseNet(detector, segmenter, preset, mean_db=float(first_log_power.mean()),
                    std_db=float(first_log_power.std()), score_threshold=0.0)


KERNEL_KEYS = ("native", "torch")  # the keys of the results: the compiled and the reference sparse engine
SPARSE_ENGINE = {"native": "compiled", "torch": "reference"}  # models.sparse.compiled's names


@torch.no_grad()
def erasenet_run(preset: str, n_frames: int, repeats: int, *, random_weights: bool = False) -> dict:
    """ERASE-Net end to end on the compiled engine, with ``torch_engine``: the same on the pure-PyTorch one."""
    frames = list(simulate_sequence(preset, n_frames, seed=5))
    cubes = [frame.log_power() for frame in frames]
    net = build_erasenet(preset, cubes[0], random_weights=random_weights)
    for engine in KERNEL_KEYS:  # warm-up: the detector's meta copy for its MAC count, first maps, the engine's build
        with compiled.using_kernels(SPARSE_ENGINE[engine]):
            net.segment(cubes[0], kind=InputKind.log_power)
    times, macs, macs_paper, executed = {engine: [] for engine in KERNEL_KEYS}, [], [], []
    stages: dict[str, list[float]] = {}  # the compiled engine's seconds per stage (FrameCompute.seconds)
    r, a, d = net.profile.shape
    detector = count_macs(net.detector, (1, d, r, a))
    for frame, cube in zip(frames, cubes, strict=True):
        if random_weights:  # top-K seeds: the ROI a trained detector would grow
            net.max_objects = max(1, sum(1 for o in frame.objects if o.n_voxels))
        for _ in range(repeats):
            for engine in reversed(KERNEL_KEYS):  # the compiled engine last: its result's MACs are kept below
                with compiled.using_kernels(SPARSE_ENGINE[engine]):
                    started = time.perf_counter()
                    result = net.segment(cube, kind=InputKind.log_power)
                    times[engine].append(time.perf_counter() - started)
            for stage, seconds in result.compute.seconds.items():
                stages.setdefault(stage, []).append(seconds)
        macs.append(result.compute.macs_total)
        executed.append(result.compute.executed_macs_total)
        macs_paper.append(result.compute.macs_total + detector.macs_paper - detector.macs)
    engine = "native" if compiled.available() else "torch (the compiled engine did not build)"
    return {"median_s": statistics.median(times["native"]), "min_s": min(times["native"]),
            "runs": len(times["native"]), "sparse_engine": engine,
            "torch_engine": {"median_s": statistics.median(times["torch"]), "min_s": min(times["torch"])},
            "stages_ms": {stage: 1e3 * statistics.median(values) for stage, values in stages.items()},
            "macs": float(np.mean(macs)), "macs_paper": float(np.mean(macs_paper)),
            "executed_macs": float(np.mean(executed)),
            "params": int(sum(net.params.values())), "roi_voxels_last": int(result.compute.roi_voxels),
            "weights": "random, top-K seeds" if random_weights else " + ".join(
                str(path.relative_to(REPO)) for path in SHIPPED_PAIRS[preset])}


@torch.no_grad()
def optimised_latency(key: str, preset: str, repeats: int) -> dict:
    """A baseline's forward with the detector's inference optimisations (BatchNorms folded, channels_last,
    traced), batch 1, random weights and inputs."""
    name, config = MODELS[key]
    model = create_model(name, preset=preset, **config).eval()
    shapes = input_shapes(model, preset)
    model = copy.deepcopy(model)
    folded = fold_batch_norms(model)
    for module in model.modules():  # TMVA-Net's 3-D convs have no channels_last form: 2-D layers only
        if isinstance(module, (torch.nn.Conv2d, torch.nn.ConvTranspose2d, torch.nn.BatchNorm2d)):
            module.to(memory_format=torch.channels_last)
    inputs = tuple(torch.randn(shape).contiguous(memory_format=torch.channels_last) for shape in shapes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        graph = torch.jit.trace(model, inputs, strict=False)
    return {**time_call(lambda: graph(*inputs), repeats), "folded_batch_norms": folded}


def baseline_run(key: str, preset: str, repeats: int) -> dict:
    name, config = MODELS[key]
    model = create_model(name, preset=preset, **config)
    report = count_macs(model, *input_shapes(model, preset))
    eager = latency(key, preset, repeats)
    return {**optimised_latency(key, preset, repeats), "eager_median_s": eager["median_s"],
            "macs": float(report.macs), "macs_paper": float(report.macs_paper), "params": report.params,
            "weights": "random", "form": "BatchNorms folded, channels_last, traced (eager time beside)"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="small", choices=["small", "carrada"])
    parser.add_argument("--frames", type=int, default=8, help="ERASE-Net: simulated frames")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--random-weights", action="store_true",
                        help="ERASE-Net with random weights and top-K seeds instead of the preset's shipped pair")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "compare.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    rows = {"erasenet": erasenet_run(args.preset, args.frames, args.repeats, random_weights=args.random_weights)}
    for key in ROWS:
        rows[key] = baseline_run(key, args.preset, args.repeats)
    unet = {k: rows["unet_rd"][k] + rows["unet_ra"][k]
            for k in ("median_s", "min_s", "eager_median_s", "macs", "macs_paper", "params")}
    rows["unet_pair"] = {**unet, "weights": "random", "note": "U-Net RD + U-Net RA (one network per view)"}
    reference = rows["erasenet"]
    for row in rows.values():
        row["latency_ratio"] = row["median_s"] / reference["median_s"]
        row["macs_ratio"] = row["macs"] / reference["macs"]
        row["gmacs_per_s"] = row["macs"] / row["median_s"] / 1e9
    for row in rows.values():
        row["gmacs_per_s_ratio_to_erasenet"] = reference["gmacs_per_s"] / row["gmacs_per_s"]
    names = {"erasenet": "ERASE-Net (end to end)", **ROWS, "unet_pair": "U-Net RD + RA"}
    torch_engine = reference["torch_engine"]
    torch_engine["latency_ratio"] = torch_engine["median_s"] / reference["median_s"]
    torch_engine["gmacs_per_s"] = reference["macs"] / torch_engine["median_s"] / 1e9
    print(f"{args.preset}, {args.threads} torch thread(s), sparse engine {reference['sparse_engine']} "
          f"(pure-PyTorch engine: {torch_engine['median_s'] * 1e3:.1f} ms/frame, {torch_engine['latency_ratio']:.2f}x; "
          f"TMVA-Net {rows['tmvanet']['median_s'] / torch_engine['median_s']:.1f}x it)")
    stage_ms = ", ".join(f"{stage} {ms:.1f}" for stage, ms in reference["stages_ms"].items())
    print(f"ERASE-Net stages, median ms: {stage_ms}")
    print(f"{'model':24} {'params':>11} {'GMACs':>8} {'[paper]':>8} {'ms/frame':>9} {'(eager)':>8} "
          f"{'x ERASE-Net':>12} {'x MACs':>8} {'GMAC/s':>7}")
    for key, row in rows.items():
        eager = f"{row['eager_median_s'] * 1e3:8.1f}" if "eager_median_s" in row else f"{'':8}"
        print(f"{names[key]:24} {row['params']:>11,} {row['macs'] / 1e9:8.3f} {row['macs_paper'] / 1e9:8.3f} "
              f"{row['median_s'] * 1e3:9.1f} {eager} {row['latency_ratio']:12.1f} {row['macs_ratio']:8.1f} "
              f"{row['gmacs_per_s']:7.1f}")
    result = {
        "preset": args.preset, "rows": {names[k]: row for k, row in rows.items()},
        "latency": "seconds per frame, median; ERASE-Net over frames x repeats, baselines over repeats, batch 1",
        "macs_conventions": {"macs": "correct (FlopCounterMode FLOPs / 2)",
                             "macs_paper": "transposed convs counted per output position (paper/thop)"},
        "ratios": "latency_ratio and macs_ratio are the row's figure over ERASE-Net's, measured in this run; "
                  "gmacs_per_s_ratio_to_erasenet is ERASE-Net's GMAC/s over the row's",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "threads": args.threads,
                    "cpu_flags": [f for f in compiled.cpu_flags().split() if f.startswith(("avx", "fma", "sse4"))],
                    "torch": torch.__version__, "load_average_before": load_before,
                    "load_average_after": os.getloadavg(),
                    "note": "shared 2-core CPU, other jobs running beside the benchmark"},
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
