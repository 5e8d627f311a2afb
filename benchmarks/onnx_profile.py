"""Where an int8 frame's time goes: each stage of a frame on the float ONNX, int8 ONNX and default engines, and the
segmenter graph's time by operator type (onnxruntime's own profiler), side by side on the same frames.

    nice -n 5 .venv/bin/python -m benchmarks.onnx_profile --store out/stage1/seed25440.zarr \
        --calibration out/edge-calib.zarr

The edge table (``benchmarks/edge.py``) gives each engine's end-to-end time; this splits it, so that what stands
between the int8 graphs and the default engine is a figure: per stage (``FrameCompute.seconds``: transform,
detect, grow, segment, project; each frame's fastest of ``--repeats`` runs, engines interleaved, median over
frames), the segment stage of the ONNX engines split into its kernel maps (the same on both: the compiled
engine's, numpy's beside them) and the graph run, and the graph run split by operator type over the same ROIs (a
second session per graph with profiling on; its sums run 1.3-1.5x above the plain run's, the profiler's own cost
per node, so read its shares). ``ceiling`` is the int8 frame less its profiled matrix products: what the int8
arithmetic could save at most. ``segment_cpu_ms``: the segmenter on each ROI in this thread's CPU time (best of
``--repeats``, at least 3, median over frames; on a shared machine it moves far less than the wall clock): the
torch engine's network (its kernel maps included), the float ONNX engine's kernel maps and graph, and beside them
the float graph in its export format 5 form (27 rows gathered per voxel: the ratio is what format 6's z-column
gathers gained).

Writes ``benchmarks/results/onnx_profile.json`` with the CPU's flags and the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from benchmarks.edge import PAIRS, ROOT, engine_parser, one_thread_results, pair_engines, spread_frames
from benchmarks.harness import write_with_load
from models.checkpoint import load_pair
from models.erasenet.compute_report import STEPS
from models.export.kernel_maps_compiled import fastest_kernel_maps
from models.export.kernel_maps_numpy import kernel_maps
from models.export.onnx_export import export_segmenter
from radar.input_kind import InputKind

RUNTIMES = ("onnx", "onnx-int8", "torch")
PRODUCTS = ("MatMul", "QLinearMatMul", "MatMulInteger", "MatMulIntegerToFloat", "Gemm", "QGemm",
            "DynamicQuantizeMatMul", "FusedMatMul")
"""Operator types that are a graph's matrix products (float or 8-bit), for the ceiling."""


def stage_times(nets: dict, cubes: list[np.ndarray], repeats: int) -> tuple[dict, list]:
    """Per engine, the median over frames of each stage's seconds in the frame's fastest run; and every ROI the
    ONNX engine's segmenter graph was fed (coords, features), one per frame."""
    best: dict[str, list[dict[str, float]]] = {name: [] for name in nets}
    feeds: list[tuple[np.ndarray, np.ndarray]] = []
    original = nets["onnx"].voxel_logits

    def recording(coords: np.ndarray, features: np.ndarray):  # the float engine's feeds, once per frame
        if len(feeds) < len(best["onnx"]) + 1:
            feeds.append((coords.copy(), features.copy()))
        return original(coords, features)

    nets["onnx"].voxel_logits = recording
    for index, cube in enumerate(cubes):
        runs: dict[str, list[dict[str, float]]] = {name: [] for name in nets}
        for repeat in range(repeats):
            order = list(nets) if (index + repeat) % 2 == 0 else list(nets)[::-1]
            for name in order:
                runs[name].append(dict(nets[name].segment(cube, kind=InputKind.log_power).compute.seconds))
        for name in nets:
            best[name].append(min(runs[name], key=lambda seconds: sum(seconds.values())))
    nets["onnx"].voxel_logits = original
    medians = {name: {stage: 1e3 * statistics.median(run.get(stage, 0.0) for run in runs) for stage in STEPS}
               for name, runs in best.items()}
    for name in medians:
        medians[name]["total"] = 1e3 * statistics.median(sum(run.values()) for run in best[name])
    return medians, feeds


def segment_split(nets: dict, feeds: list, repeats: int) -> dict[str, float]:
    """Median ms over the ROIs of the kernel maps (numpy's, and the compiled ones the engine uses) and of each
    ONNX engine's segmenter graph run."""
    maps_ms: dict[str, list[float]] = {"kernel_maps_numpy": [], "kernel_maps_compiled": []}
    run_ms: dict[str, list[float]] = {name: [] for name in ("onnx", "onnx-int8")}
    for coords, features in feeds:
        for name, build in (("kernel_maps_numpy", kernel_maps), ("kernel_maps_compiled", fastest_kernel_maps)):
            started = time.perf_counter()
            maps = build(coords)
            maps_ms[name].append(time.perf_counter() - started)
        for name in run_ms:
            session = nets[name]._segmenter_session
            times = []
            for _ in range(repeats):
                started = time.perf_counter()
                session.run(None, {"features": features, **maps})
                times.append(time.perf_counter() - started)
            run_ms[name].append(min(times))
    out = {name: 1e3 * statistics.median(times) for name, times in maps_ms.items()}
    out.update({f"graph_{name}": 1e3 * statistics.median(times) for name, times in run_ms.items()})
    return out


def segment_cpu(nets: dict, feeds: list, repeats: int, rows_graph: Path) -> dict[str, float]:
    """Median over the ROIs of each ROI's best thread CPU time (ms): the torch engine's segmenter network (kernel
    maps included), the float ONNX engine's kernel maps and graph run, and the float graph with 27-row gathers."""
    import onnxruntime as ort
    import torch

    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    options.log_severity_level = 3
    rows = ort.InferenceSession(str(rows_graph), options, providers=["CPUExecutionProvider"])
    torch_net, session = nets["torch"], nets["onnx"]._segmenter_session
    best: dict[str, list[float]] = {name: [] for name in ("torch_network", "onnx_maps", "onnx_graph",
                                                          "onnx_graph_rows")}
    for coords, features in feeds:
        sparse_coords = torch.from_numpy(np.hstack([np.zeros((len(coords), 1), np.int64), coords.astype(np.int64)]))
        times: dict[str, list[float]] = {name: [] for name in best}
        steps = [("torch", None), ("onnx", session), ("rows", rows)]
        for repeat in range(repeats):
            for name, graph in (steps if repeat % 2 == 0 else steps[::-1]):
                started = time.thread_time()
                if graph is None:
                    with torch.no_grad():
                        torch_net.segmenter_form(torch_net.segmenter.make_input(sparse_coords,
                                                                                torch.from_numpy(features)))
                    times["torch_network"].append(time.thread_time() - started)
                    continue
                maps = fastest_kernel_maps(coords)
                mapped = time.thread_time()
                graph.run(None, {"features": features, **maps})
                done = time.thread_time()
                if name == "onnx":
                    times["onnx_maps"].append(mapped - started)
                    times["onnx_graph"].append(done - mapped)
                else:
                    times["onnx_graph_rows"].append(done - mapped)
        for name in best:
            best[name].append(min(times[name]))
    out = {name: 1e3 * statistics.median(values) for name, values in best.items()}
    out["onnx_over_torch"] = (out["onnx_maps"] + out["onnx_graph"]) / out["torch_network"]
    out["graph_over_rows_graph"] = out["onnx_graph"] / out["onnx_graph_rows"]
    return out


def operator_profile(path: Path, feeds: list, fold_weights: bool = False) -> dict[str, float]:
    """ms per ROI by operator type of one graph over ``feeds`` (onnxruntime's profiler, one thread)."""
    import onnxruntime as ort

    from models.export.compact import FOLD_WEIGHTS

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    if fold_weights:
        options.add_session_config_entry(*FOLD_WEIGHTS)
    with tempfile.TemporaryDirectory(prefix="ort-profile-") as directory:
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(directory) / "profile")
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        for feed in feeds:
            session.run(None, feed)
        trace = json.loads(Path(session.end_profiling()).read_text())
    by_type: dict[str, float] = defaultdict(float)
    for event in trace:
        if event.get("cat") == "Node" and event.get("name", "").endswith("_kernel_time"):
            by_type[event["args"]["op_name"]] += event["dur"] / 1e3 / len(feeds)
    return dict(sorted(by_type.items(), key=lambda item: -item[1]))


def detector_feeds(net, cubes: list[np.ndarray]) -> list[dict[str, np.ndarray]]:  # noqa: ANN001
    """The detector graph's inputs for each cube (a graph that reads earlier frames: the cube before it in the list
    as its earlier frame; the operators' times do not depend on which frame it is)."""
    feeds = []
    for index, cube in enumerate(cubes):
        history = net._history_input([cubes[index - 1]]) if net.history_frames and index else {}
        feeds.append(net._run_detector.feed(np.ascontiguousarray(cube, dtype=np.float32), **history))
    return feeds


def profile_pair(pair: str, args: argparse.Namespace, cubes: list[np.ndarray], cache: Path) -> dict:
    float_dir, int8_dir, nets = pair_engines(pair, cache, args.calibration, args.calibration_frames,
                                             tuple(args.methods), cubes[0])
    stages, feeds = stage_times(nets, cubes, args.repeats)
    split = segment_split(nets, feeds, args.repeats)
    with tempfile.TemporaryDirectory(prefix="onnx-rows-") as directory:  # not in the export cache: it checks files
        rows_graph = Path(directory) / "segmenter.onnx"  # the float graph's export format 5 form, for comparison
        export_segmenter(load_pair(*(ROOT / path for path in PAIRS[pair]))[1].build().eval(),
                         nets["onnx"].profile, rows_graph)
        cpu = segment_cpu(nets, feeds, max(args.repeats, 3), rows_graph)
    graph_feeds = [{"features": features, **kernel_maps(coords)} for coords, features in feeds]
    int8_manifest = json.loads((int8_dir / "manifest.json").read_text())
    fold = int8_manifest["detector"].get("precision") == "int8-weights"
    operators = {
        "segmenter": {"float": operator_profile(float_dir / "segmenter.onnx", graph_feeds),
                      "int8": operator_profile(int8_dir / "segmenter.onnx", graph_feeds)},
        "detector": {"float": operator_profile(float_dir / "detector.onnx", detector_feeds(nets["onnx"], cubes)),
                     "int8": operator_profile(int8_dir / "detector.onnx", detector_feeds(nets["onnx"], cubes), fold)},
    }
    int8_products = sum(ms for op, ms in operators["segmenter"]["int8"].items() if op in PRODUCTS)
    int8_products += sum(ms for op, ms in operators["detector"]["int8"].items() if op in ("QLinearConv", "Conv"))
    ceiling = stages["onnx-int8"]["total"] - int8_products
    return {"detector": PAIRS[pair][0], "segmenter": PAIRS[pair][1],
            "roi_voxels": [int(len(coords)) for coords, _ in feeds],
            "stages_ms": stages, "segment_split_ms": split, "segment_cpu_ms": cpu, "operators_ms": operators,
            "ceiling": {"int8_products_ms": int8_products, "int8_without_products_ms": ceiling,
                        "torch_ms": stages["torch"]["total"],
                        "int8_without_products_over_torch": ceiling / stages["torch"]["total"]}}


def print_pair(pair: str, entry: dict) -> None:
    stages = entry["stages_ms"]
    print(f"\n{pair}: ROI voxels {entry['roi_voxels']}")
    print(f"{'stage':>10} " + " ".join(f"{name:>10}" for name in RUNTIMES))
    for stage in (*STEPS, "total"):
        print(f"{stage:>10} " + " ".join(f"{stages[name][stage]:10.2f}" for name in RUNTIMES))
    print("segment split (ms):", {key: round(value, 2) for key, value in entry["segment_split_ms"].items()})
    print("segment CPU time (ms):", {key: round(value, 3) for key, value in entry["segment_cpu_ms"].items()})
    for graph, precisions in entry["operators_ms"].items():
        for precision, ops in precisions.items():
            top = ", ".join(f"{op} {ms:.2f}" for op, ms in list(ops.items())[:8])
            print(f"{graph} {precision}: total {sum(ops.values()):.2f} ms: {top}")
    print("ceiling:", {key: round(value, 3) for key, value in entry["ceiling"].items()})


def main() -> None:
    parser = engine_parser(__doc__, store_help="store whose frames are timed (a fresh seed)", methods=["Percentile"],
                           pairs=["shipped"], results="onnx_profile.json")
    parser.add_argument("--frames", type=int, default=8)
    args = parser.parse_args()
    results = {**one_thread_results(args), "frames": args.frames, "repeats": args.repeats, "pairs": {}}
    cache = Path(args.cache or tempfile.mkdtemp(prefix="onnx-profile-"))
    _, cubes = spread_frames(args.store, args.frames)
    for pair in args.pairs:
        results["pairs"][pair] = entry = profile_pair(pair, args, cubes, cache)
        print_pair(pair, entry)
    write_with_load(results, args.out)


if __name__ == "__main__":
    main()
