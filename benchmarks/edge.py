"""int8 on the edge: the shipped pair and the slimmed pair, float and int8 ONNX graphs, against the default engine.

    nice -n 5 .venv/bin/python -m benchmarks.edge --store /tmp/edge.zarr --calibration /tmp/edge-calib.zarr

Per pair: parameters, bytes on disk of both .onnx files, MACs (the detector's per frame, the segmenter's useful
MACs as the mean over the timed frames), the median over ``--timing-frames`` frames of each frame's best of
``--repeats`` end-to-end times on one thread, the ONNX float, ONNX int8 and default (``torch``) engines
interleaved per frame; then RA / RD mIoU, pedestrian IoU and mAP of the float and int8 graphs on every frame of
``--store`` (a store of a seed nobody trained on) with ``pipelines.evaluation.evaluate``, whose detection AP comes
from the engine being scored (``EraseNet.detect``: the ONNX detector graph on the ONNX engines). The int8 graphs
are calibrated on ``--calibration-frames`` frames of the train split of ``--calibration`` (another seed), with the
``--methods`` given (default all three; ``--methods Percentile`` alone to save minutes per pair).

Writes benchmarks/results/edge.json with the CPU's flags (AVX-512 VNNI or not) and the load average before and
after: the machine is shared, so compare engines within one run.
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

from benchmarks.harness import write_with_load
from models.checkpoint import load_pair
from models.export.export_cache import exported_dir
from models.export.quantize import METHODS
from models.runtime import load_erasenet
from pipelines.datasets.calibration import store_calibration
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.store import frames_of_split, open_store
from radar.input_kind import InputKind

ROOT = Path(__file__).resolve().parents[1]
PAIRS = {"shipped": ("checkpoints/detector.pt", "checkpoints/segmenter.pt"),
         "p40": ("checkpoints/detector-slimmed.pt", "checkpoints/segmenter-slimmed.pt")}
RUNTIMES = ("onnx", "onnx-int8", "torch")


def cpu_flags() -> dict[str, object]:
    """The CPU's model and the SIMD flags int8 kernels depend on (from /proc/cpuinfo)."""
    flags: set[str] = set()
    model = platform.processor()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
            elif line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
    wanted = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")
    return {"model": model, "flags": {name: name in flags for name in wanted},
            "vnni": "avx512_vnni" in flags or "avx_vnni" in flags, "cores": os.cpu_count()}


def engine_parser(doc: str, *, store_help: str, methods: list[str], pairs: list[str],
                  results: str) -> argparse.ArgumentParser:
    """The command line ``edge`` and ``onnx_profile`` share: ``--store``, the options of :func:`pair_engines`, the
    timing repeats and ``--out`` (default ``benchmarks/results/RESULTS``); each adds its frame counts."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--store", required=True, help=store_help)
    parser.add_argument("--calibration", required=True, help="calibration store (its train split)")
    parser.add_argument("--calibration-frames", type=int, default=6)
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=methods,
                        help="calibration methods tried (the best ROI label agreement is kept)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--pairs", nargs="+", choices=sorted(PAIRS), default=pairs)
    parser.add_argument("--cache", default=None, help="export cache (default: a temporary directory)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / results))
    return parser


def one_thread_results(args: argparse.Namespace) -> dict[str, object]:
    """Sets torch to one thread; the figures' opening entries: CPU, load average before, threads, both stores."""
    torch.set_num_threads(1)
    return {"cpu": cpu_flags(), "load_average_before": os.getloadavg(), "threads": 1, "store": args.store,
            "calibration_store": args.calibration}


def spread_frames(store: str, frames: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """``frames`` slots spread evenly over every frame of ``store`` and their cubes (log power, float32)."""
    root = open_store(store)
    slots = frames_of_split(root, None)
    chosen = slots[np.linspace(0, len(slots) - 1, min(frames, len(slots))).round().astype(int)]
    return chosen, [np.asarray(root["input"][int(slot)], dtype=np.float32) for slot in chosen]


def pair_engines(pair: str, cache: Path, calibration_store: str, calibration_frames: int, methods: tuple[str, ...],
                 warm_up: np.ndarray) -> tuple[Path, Path, dict]:
    """A pair's float and int8 exports (made in ``cache`` if absent) and its three engines, each run once on
    ``warm_up``: (float dir, int8 dir, {"onnx", "onnx-int8", "torch": EraseNet})."""
    detector, segmenter = load_pair(*(ROOT / path for path in PAIRS[pair]))
    float_dir = exported_dir(detector, segmenter, cache)
    profile = load_erasenet(detector, segmenter, runtime="onnx", onnx_dir=float_dir).profile
    calibration = store_calibration(calibration_store, profile, frames=calibration_frames, methods=methods)
    int8_dir = exported_dir(detector, segmenter, cache, int8=calibration)
    nets = {"onnx": load_erasenet(detector, segmenter, runtime="onnx", onnx_dir=float_dir),
            "onnx-int8": load_erasenet(detector, segmenter, runtime="onnx-int8", onnx_dir=int8_dir),
            "torch": load_erasenet(detector, segmenter)}
    for net in nets.values():
        net.segment(warm_up, kind=InputKind.log_power)
    return float_dir, int8_dir, nets


def store_history(store: str, slots: np.ndarray, history_frames: int) -> list[list[np.ndarray | None] | None]:
    """Each slot's earlier frames in ``store`` (what a detector that reads ``history_frames`` gets; None: none)."""
    if not history_frames:
        return [None] * len(slots)
    root = open_store(store)
    earlier = earlier_slots(root, history_frames)
    return [earlier_frames(root["input"], earlier[int(slot)]) for slot in slots]


def timing(nets: dict, cubes: list[np.ndarray], repeats: int,
           histories: list[list[np.ndarray | None] | None] | None = None) -> dict[str, object]:
    """Median over frames of each frame's best end-to-end time per engine (interleaved), and segment MACs;
    ``histories``: each frame's earlier frames, given to every engine (they all read them)."""
    best: dict[str, list[float]] = {name: [] for name in nets}
    macs: list[int] = []
    for index, cube in enumerate(cubes):
        times: dict[str, list[float]] = {name: [] for name in nets}
        for repeat in range(repeats):
            order = list(nets) if (index + repeat) % 2 == 0 else list(nets)[::-1]
            for name in order:
                started = time.perf_counter()
                result = nets[name].segment(cube, kind=InputKind.log_power,
                                            history=None if histories is None else histories[index])
                times[name].append(time.perf_counter() - started)
                if name == "onnx" and repeat == 0:
                    macs.append(result.compute.segment_macs)
        for name in nets:
            best[name].append(min(times[name]))
    median = {name: statistics.median(values) for name, values in best.items()}
    return {"median_seconds": median,
            "onnx_float_over_int8": median["onnx"] / median["onnx-int8"],
            "torch_over_int8": median["torch"] / median["onnx-int8"],
            "torch_over_onnx_float": median["torch"] / median["onnx"],
            "segment_useful_macs_mean": float(np.mean(macs)) if macs else 0.0}


def accuracy(detector: str, segmenter: str, store: str, engine: str, onnx_dir: Path, frames: int) -> dict:
    """RA / RD mIoU, pedestrian IoU and mAP of one engine on the store (``pipelines.evaluation.evaluate``)."""
    from pipelines.evaluation.evaluate import EvaluateConfig, evaluate

    with tempfile.TemporaryDirectory(prefix="edge-eval-") as out:
        metrics = evaluate(EvaluateConfig(
            detector=detector, segmenter=segmenter, store=store, out=out, split=None, max_frames=frames, pictures=0,
            sweep_frames=0, oracle=False, threads=1, progress=False, engine=engine,
            onnx_dir=None if engine == "torch" else str(onnx_dir)))
    segmentation = metrics["segmentation"]
    return {"frames": metrics["frames"], "RA_mIoU": segmentation["RA"]["mIoU"], "RD_mIoU": segmentation["RD"]["mIoU"],
            "RA_pedestrian_IoU": segmentation["RA"]["iou"]["pedestrian"],
            "RD_pedestrian_IoU": segmentation["RD"]["iou"]["pedestrian"], "mAP": metrics["detection"]["mAP"]}


def main() -> None:
    parser = engine_parser(__doc__, store_help="evaluation store (a fresh seed), every frame scored",
                           methods=list(METHODS), pairs=list(PAIRS), results="edge.json")
    parser.add_argument("--eval-frames", type=int, default=0, help="0: every frame of --store")
    parser.add_argument("--timing-frames", type=int, default=8)
    args = parser.parse_args()
    results = {**one_thread_results(args), "calibration_frames": args.calibration_frames, "methods": args.methods,
               "mAP_from": "the engine scored (EraseNet.detect: ONNX detector graph on ONNX)", "pairs": {}}
    cache = Path(args.cache or tempfile.mkdtemp(prefix="edge-onnx-"))
    chosen, cubes = spread_frames(args.store, args.timing_frames)
    for pair in args.pairs:
        detector, segmenter = (str(ROOT / path) for path in PAIRS[pair])
        float_dir, int8_dir, nets = pair_engines(pair, cache, args.calibration, args.calibration_frames,
                                                 tuple(args.methods), cubes[0])
        manifests = {"float": json.loads((float_dir / "manifest.json").read_text()),
                     "int8": json.loads((int8_dir / "manifest.json").read_text())}
        entry: dict[str, object] = {
            "detector": PAIRS[pair][0], "segmenter": PAIRS[pair][1],
            "params": {stage: manifests["float"][stage]["params"] for stage in ("detector", "segmenter")},
            "detector_macs": manifests["float"]["detector"]["macs"],
            "bytes": {precision: {stage: (directory / f"{stage}.onnx").stat().st_size
                                  for stage in ("detector", "segmenter")}
                      for precision, directory in (("float", float_dir), ("int8", int8_dir))},
            "quantization": manifests["int8"]["quantization"],
            "graph_precision": {stage: manifests["int8"][stage].get("precision", "int8")
                                for stage in ("detector", "segmenter")},
            "operator_precision": {stage: manifests["int8"][stage]["operator_precision"]
                                   for stage in ("detector", "segmenter")},
        }
        histories = store_history(args.store, chosen, nets["torch"].history_frames)
        entry["timing"] = timing(nets, cubes, args.repeats, histories)
        entry["timing"]["history_frames"] = nets["torch"].history_frames
        entry["timing"]["frames"] = [int(s) for s in chosen]
        print(pair, json.dumps(entry["timing"], indent=1), flush=True)
        entry["accuracy"] = {precision: accuracy(detector, segmenter, args.store, engine, directory, args.eval_frames)
                             for precision, engine, directory in (("float", "onnx", float_dir),
                                                                  ("int8", "onnx-int8", int8_dir))}
        print(pair, json.dumps(entry["accuracy"], indent=1), flush=True)
        results["pairs"][pair] = entry
    write_with_load(results, args.out)


if __name__ == "__main__":
    main()
