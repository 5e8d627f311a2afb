"""ONNX Runtime against PyTorch: the same ERASE-Net frames through both engines, side by side, one thread.

    nice -n 10 .venv/bin/python benchmarks/export.py [--frames 3] [--repeats 3] [--presets small carrada]

Per preset, each frame runs through the PyTorch engine (:class:`models.erasenet.model.EraseNet`: traced detector,
the sparse engine of ``models.sparse``) and the ONNX engine (:class:`models.export.onnx_engine.OnnxEraseNet`),
interleaved (the order alternating per repeat), in two modes: the detector's own seeds (end to end) and
seeds at the true object centres (the ROI a trained detector grows: the segment stage at a realistic
size). Reported per stage: the median over frames of each frame's best time, and the median over frames of
the per-frame torch / onnx ratio (> 1: ONNX faster); labels agreement on the ROI voxels as a check. ``small``
runs the shipped checkpoints; ``carrada`` has none, so it runs random-weight models of the registry's paper
size (detector "slim_sep", MinkUNet ratio 0.37), exported like a checkpoint (cost does not depend on the
weights; with random weights the detector seeds threshold 0, top-K = the true object count).

Then, for every shipped checkpoint pair (``--agreement-frames``, 48 by default), the engines' agreement on fresh
frames: labels on the ROI voxels, objects, the largest logit difference.

Writes benchmarks/results/export.json with the load average before and after and the CPU's flags: the
machine is shared, so compare the ratios, not the absolute times.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from models.checkpoint import Checkpoint, load_checkpoint, load_pair
from models.erasenet.model import STEPS, EraseNet
from models.export.export_cache import exported_dir
from models.export.onnx_engine import OnnxEraseNet
from models.registry import create_model
from models.sparse import SparseTensor
from radar import transforms
from radar.centres import Centres
from radar.profiles import get_profile
from radar.roi import roi_points
from radar.simulate import simulate_sequence

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = {"small": (ROOT / "checkpoints" / "detector.pt", ROOT / "checkpoints" / "segmenter.pt")}
SHIPPED_PAIRS = {"shipped": SHIPPED["small"],
                 "p40": (ROOT / "checkpoints" / "detector-slimmed.pt", ROOT / "checkpoints" / "segmenter-slimmed.pt")}
CPU_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_vnni", "amx_tile")


def cpu_description() -> dict[str, object]:
    """Model name and the vector-unit flags that decide GEMM speed (Linux /proc/cpuinfo)."""
    model, flags = platform.processor(), set()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "flags":
                flags = set(value.split())
    return {"model": model, "flags": [f for f in CPU_FLAGS if f in flags], "cores": os.cpu_count()}


def checkpoints(preset: str) -> tuple[Checkpoint, Checkpoint, str]:
    """The preset's shipped pair, or random-weight paper-size models wrapped as checkpoints."""
    if preset in SHIPPED and all(p.is_file() for p in SHIPPED[preset]):
        det, seg = (load_checkpoint(p) for p in SHIPPED[preset])
        return det, seg, "shipped checkpoints"
    torch.manual_seed(0)
    profile = get_profile(preset)
    made = []
    for name, config in (("centre_detector", {"preset": preset}), ("minkunet", {"preset": preset})):
        model = create_model(name, **config).eval()
        made.append(Checkpoint(name, config, model.state_dict(), preset, tuple(profile.all_class_names),
                               {"mean": 60.0, "std": 8.0}))
    return made[0], made[1], "random weights, registry paper size (detector slim_sep, MinkUNet ratio 0.37)"


def true_seeds(frame) -> Centres:
    return Centres.from_bins(np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin]
                                       for o in frame.objects if o.n_voxels]).reshape(-1, 3))


def bench_preset(preset: str, n_frames: int, repeats: int, cache: Path) -> dict[str, object]:
    det, seg, source = checkpoints(preset)
    random_weights = source.startswith("random")
    kwargs = {"score_threshold": 0.0} if random_weights else {}
    started = time.perf_counter()
    onnx_dir = exported_dir(det, seg, root=cache)
    export_seconds = time.perf_counter() - started
    engines = {"torch": EraseNet.from_checkpoints(det, seg, **kwargs),
               "onnx": OnnxEraseNet.from_checkpoints(det, seg, onnx_dir=onnx_dir, **kwargs)}
    frames = list(simulate_sequence(preset, n_frames, seed=2026))
    for net in engines.values():  # warm-up: first calls allocate, trace, and count the detector's MACs
        net.segment(frames[0].cube)
    best: dict[str, dict[str, list[dict[str, float]]]] = {m: {e: [] for e in engines} for m in ("detector_seeds",
                                                                                                   "true_seeds")}
    agreement, roi_voxels, macs = [], {"detector_seeds": [], "true_seeds": []}, {}
    for frame in frames:
        for net in engines.values():
            if random_weights:
                net.max_objects = max(1, len(frame.objects))
        for mode in best:
            centres = true_seeds(frame) if mode == "true_seeds" else None
            times: dict[str, list[dict[str, float]]] = {e: [] for e in engines}
            results = {}
            for repeat in range(repeats):
                order = list(engines) if repeat % 2 == 0 else list(engines)[::-1]
                for name in order:
                    results[name] = engines[name].segment(frame.cube, centres=centres)
                    times[name].append(results[name].compute.seconds_by_stage())
            for name in engines:  # this frame's best time of every stage
                best[mode][name].append({s: min(t[s] for t in times[name]) for s in (*STEPS, "total")})
            roi = tuple(results["torch"].regions.voxels.T)
            roi_voxels[mode].append(len(results["torch"].regions))
            if len(results["torch"].regions):
                agreement.append(float((results["onnx"].labels[roi] == results["torch"].labels[roi]).mean()))
            macs = {name: results[name].compute.executed_macs_by_stage() for name in engines}
    out: dict[str, object] = {"models": source, "export_seconds": export_seconds,
                              "params": engines["torch"].params, "labels_agreement_min": min(agreement),
                              "executed_macs_last_frame": macs}
    for mode, per_engine in best.items():
        stages = {}
        for stage in (*STEPS, "total"):
            torch_s = statistics.median(frame[stage] for frame in per_engine["torch"])
            onnx_s = statistics.median(frame[stage] for frame in per_engine["onnx"])
            # the median of per-frame ratios: each frame's two engines ran interleaved, under the same load
            ratios = [t[stage] / o[stage] for t, o in zip(per_engine["torch"], per_engine["onnx"], strict=True)
                      if o[stage] > 0]
            stages[stage] = {"torch_ms": torch_s * 1e3, "onnx_ms": onnx_s * 1e3,
                             "torch_over_onnx": statistics.median(ratios) if ratios else None}
        out[mode] = {"roi_voxels_median": statistics.median(roi_voxels[mode]), "stages": stages}
    return out


def agreement(pair: tuple[Path, Path], n_frames: int, cache: Path) -> dict[str, object]:
    """Both engines on ``n_frames`` fresh frames of the pair's preset: label agreement on the ROI voxels, frames
    whose objects (class, voxels) are identical, the largest logit difference on the ROI points."""
    det, seg = load_pair(*pair)
    reference = EraseNet.from_checkpoints(det, seg)
    onnx = OnnxEraseNet.from_checkpoints(det, seg, onnx_dir=exported_dir(det, seg, root=cache))
    fractions, same_objects, logit_diff, voxels = [], 0, 0.0, 0
    for frame in simulate_sequence(reference.profile.name, n_frames, seed=4848):
        expected, got = reference.segment(frame.cube), onnx.segment(frame.cube)
        roi = tuple(expected.regions.voxels.T)
        voxels += len(expected.regions)
        if len(expected.regions):
            fractions.append(float((got.labels[roi] == expected.labels[roi]).mean()))
            points = roi_points(expected.regions.voxels, transforms.log_power(frame.cube), reference.profile,
                                mean_db=reference.mean_db, std_db=reference.std_db)
            coords = torch.from_numpy(np.hstack([np.zeros((len(points), 1), np.int64), points.coords]))
            with torch.no_grad():
                torch_logits = reference.segmenter(SparseTensor(coords, torch.from_numpy(points.features))).numpy()
            onnx_logits = onnx.voxel_logits(points.coords, points.features)[0]
            logit_diff = max(logit_diff, float(np.abs(onnx_logits - torch_logits).max()))
        same_objects += [(o.class_id, o.n_voxels) for o in got.objects] == [(o.class_id, o.n_voxels)
                                                                            for o in expected.objects]
    return {"frames": n_frames, "roi_voxels": voxels, "labels_equal_min": min(fractions),
            "labels_equal_mean": float(np.mean(fractions)), "frames_with_same_objects": same_objects,
            "logits_max_abs_diff": logit_diff}


def format_table(results: dict[str, object]) -> str:
    lines = []
    for preset, result in results["presets"].items():
        for mode in ("detector_seeds", "true_seeds"):
            row = result[mode]
            lines.append(f"{preset} {mode} (ROI {row['roi_voxels_median']:.0f} voxels; {result['models']}):")
            for stage, t in row["stages"].items():
                ratio = t["torch_over_onnx"]
                lines.append(f"  {stage:>9}  torch {t['torch_ms']:8.1f} ms  onnx {t['onnx_ms']:8.1f} ms  "
                             f"torch/onnx {ratio:5.2f}" if ratio else f"  {stage:>9}  (not run)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--presets", nargs="+", default=["small", "carrada"])
    parser.add_argument("--agreement-frames", type=int, default=48, help="fresh frames per shipped pair for the "
                        "agreement check (0: none)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "export.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)  # the ONNX engine takes its thread count from torch's
    results: dict[str, object] = {"threads": 1, "frames": args.frames, "repeats": args.repeats,
                                  "cpu": cpu_description(), "torch": torch.__version__,
                                  "load_average_before": os.getloadavg(), "presets": {}}
    import onnxruntime

    results["onnxruntime"] = onnxruntime.__version__
    with tempfile.TemporaryDirectory() as cache:
        for preset in args.presets:
            results["presets"][preset] = bench_preset(preset, args.frames, args.repeats, Path(cache))
            print(format_table({"presets": {preset: results["presets"][preset]}}), flush=True)
        if args.agreement_frames:
            results["agreement"] = {name: agreement(pair, args.agreement_frames, Path(cache))
                                    for name, pair in SHIPPED_PAIRS.items() if all(p.is_file() for p in pair)}
            print(json.dumps(results["agreement"], indent=2), flush=True)
    results["load_average_after"] = os.getloadavg()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    print(f"load average before {results['load_average_before']}, after {results['load_average_after']}; "
          f"written to {args.out}")


if __name__ == "__main__":
    main()
