"""The ``radarseg`` command line: each command is a thin shell over a function of pipelines/."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from typing import Any, NamedTuple

from pipelines.jobs import USER_ERRORS, report_error, run_job, with_defaults_shown
from pipelines.radar_option import RADAR_HELP, add_radar_option
from pipelines.runtime_option import add_runtime_option, runtime_of
from radar.centres import SCORE_THRESHOLD
from radar.errors import UserError
from radar.input_kind import InputKind
from radar.profiles import BUILTIN_PRESETS


class Job(NamedTuple):
    """A job command (:mod:`pipelines.jobs`' contract): the module that runs it, its one-line help, and the module
    that declares its options, which loads neither torch nor zarr (``--help`` answers at once)."""

    module: str
    help: str
    options: str


# The jobs: command -> Job. A job module loads only when its command runs, after its options have parsed.
JOBS: dict[str, Job] = {
    "preprocess": Job("pipelines.datasets.preprocess", "Ray job: cubes into the zarr store of inputs and targets",
                      "pipelines.datasets.preprocess_options"),
    "segment-batch": Job("pipelines.inference.segment_batch", "Ray job: segment a store split or a recording into a "
                                                               "predictions store",
                         "pipelines.inference.segment_batch_options"),
    "train": Job("pipelines.training.train", "train the detector or the segmenter from a store, or export a checkpoint",
                 "pipelines.training.train"),
    "train-baseline": Job("pipelines.training.train_baselines",
                          "train a 2-D baseline (unet, tmvanet, smvanet) from a store",
                          "pipelines.training.train_baselines"),
    "evaluate": Job("pipelines.evaluation.evaluate",
                    "evaluate both stages on a split of a store: metrics.json, report.md, pictures",
                    "pipelines.evaluation.evaluate_options"),
    "compare": Job("pipelines.evaluation.compare", "ERASE-Net and the 2-D baselines on the same frames: compare.json, "
                                                   "compare.md, compare_frames.png",
                   "pipelines.evaluation.compare_options"),
    "slim-sweep": Job("pipelines.training.slim_sweep", "compression sweep: prune (and fine-tune) at several ratios, "
                                                       "reports/slimming.md and .png",
                      "pipelines.training.slim_sweep_options"),
}


def job_parser_of(command: str) -> argparse.ArgumentParser:
    """The parser that reads a job command's options (``radarseg train ...``): the one its options module declares
    (:mod:`pipelines.jobs`). The top-level parser only names the jobs; the reference pages and their test walk
    these for every option."""
    from pipelines.jobs import OPTIONS, job_module, job_parser

    return job_parser(job_module(JOBS[command].options, OPTIONS), prog=f"radarseg {command}")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from pipelines.datasets.record import simulate_recording

    if args.format == "dca1000":  # each sequence a DCA1000 capture (radar/ti/recorded_capture.py)
        from pipelines.ti_commands import simulate_capture_recording

        if not args.adc:
            raise UserError("--format dca1000 writes ADC samples: add --adc")
        out = simulate_capture_recording(preset=args.profile, sequences=args.sequences, frames=args.frames,
                                         seed=args.seed, out=args.out)
        print(f"recording written to {out} (ADC as DCA1000 captures, seq_*/adc_data.bin)")
        return 0
    out = simulate_recording(preset=args.profile, sequences=args.sequences, frames=args.frames,
                             seed=args.seed, out=args.out, adc=args.adc)
    print(f"recording written to {out}")
    return 0


def _say(line: str) -> None:
    print(line, flush=True)


def _cmd_demo(args: argparse.Namespace) -> int:
    from pipelines.demo.demo import run_demo
    from pipelines.jobs import smoke_mode

    # RADARSEG_SMOKE: the same steps on 3 sequences of 2 frames, preprocessed in process, one frame segmented
    smoke = {"sequences": 3, "frames": 2, "pictures": 2, "segment_frames": 1, "in_process": True}
    started = time.perf_counter()
    result = run_demo(args.out, say=_say, **(smoke if smoke_mode() else {}))
    print(f"\nsimulated {result['frames']} frames into {result['recording']}; RA/RD pictures with labels:")
    for path in result["pictures"]:
        print(f"  {path}")
    if "store" in result:
        from pipelines.datasets.store import format_summary, summarise

        how = "in process" if result.get("preprocessed_in_process") else "with embedded Ray"
        print(f"preprocessed {how} into {result['store']} (radarseg store info {result['store']}):")
        print(format_summary(summarise(result["store"])))
    if "segmentation" in result:
        print(_format_demo_scores(result["segmentation"]))
    if "service" in result:
        from pipelines.demo.demo_service import format_service_answer

        print("the service, started on loopback and stopped again:")
        print(format_service_answer(result["service"]))
    print(f"demo done in {time.perf_counter() - started:.0f} s")
    return 0


def _format_demo_scores(segmentation: dict) -> str:
    metrics = segmentation["metrics"]
    seg, names = metrics["segmentation"], metrics["classes"]
    lines = [f"segmented with the shipped model (checkpoints/); report {segmentation['report']}:",
             segmentation["table"]]
    for view in ("RA", "RD"):
        ious = seg[view]["iou"]
        lines.append(f"  {view} IoU per class: " + ", ".join(
            f"{name} {'absent' if ious[name] is None else f'{100 * ious[name]:.1f}'}" for name in names))
    lines.append(f"These figures rest on {segmentation['frames']} frames of {segmentation['sequences']} simulated "
                 f"sequences (seed {segmentation['seed']}) that the model never saw in training; the README's come "
                 f"from 240 test frames (checkpoints/report.md), so a few points of difference are expected here.")
    lines += [f"  {path}" for path in segmentation["pictures"]]
    return "\n".join(lines)


def _is_predictions_store(path: str) -> bool:
    """Whether ``path`` holds batch segmentation's predictions (format attribute), not a preprocessed store."""
    from pathlib import Path

    from pipelines.inference.predictions_store import FORMAT

    meta = Path(path) / "zarr.json"
    try:
        return json.loads(meta.read_text()).get("attributes", {}).get("format") == FORMAT
    except (OSError, json.JSONDecodeError, UnicodeDecodeError, AttributeError):
        return False  # store.summarise says what is wrong with it


def _cmd_store_info(args: argparse.Namespace) -> int:
    from pipelines.datasets.store import format_summary, summarise

    if _is_predictions_store(args.store):
        from pipelines.inference.predictions_report import format_predictions, summarise_predictions

        format_summary, summary = format_predictions, summarise_predictions(args.store)
    else:
        summary = summarise(args.store)
    print(json.dumps(summary, indent=2) if args.json else format_summary(summary))
    return 0


def _cmd_prune(args: argparse.Namespace) -> int:
    from models.checkpoint import load_checkpoint, save_checkpoint, stored_as, stores_float16
    from models.slimming.prune import prune_checkpoint

    source = load_checkpoint(args.checkpoint)
    pruned, report = prune_checkpoint(source, ratio=args.ratio, params=args.params, macs=args.macs,
                                      min_channels=args.min_channels)
    # float16 when asked, or when the input was stored so (a shipped checkpoint): smaller on disk, like export.
    half = args.half if args.half is not None else stores_float16(source)
    path = save_checkpoint(stored_as(pruned, float16=half), args.out)
    macs = (f", MACs {report.macs_before / 1e9:.3f} G -> {report.macs_after / 1e9:.3f} G"
            if report.macs_before is not None else "")
    print(f"{args.out}: ratio {report.ratio:.3f}, {report.removed_channels}/{report.candidate_channels} channels "
          f"removed (threshold {report.threshold:.3g}), params {report.params_before:,} -> {report.params_after:,}"
          f"{macs}; stored {'float16' if half else 'float32'}, {path.stat().st_size / 1e6:.2f} MB")
    return 0


def _cmd_segment(args: argparse.Namespace) -> int:
    import json

    from pipelines.inference.segment import segment_file

    result = segment_file(args.cube, detector=args.detector, segmenter=args.segmenter,
                          input_kind=args.input, png=args.png, score_threshold=args.score_threshold,
                          runtime=runtime_of(args), warm_up=args.warm_up)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    for obj in result["objects"]:
        print(f"{obj['class_name']:>10}  score {obj['score']:.2f}  range {obj['range_m']:6.2f} m  "
              f"angle {obj['angle_deg']:6.1f} deg  v {obj['velocity_mps']:6.2f} m/s  voxels {obj['n_voxels']}")
    compute = result["compute"]
    print(f"objects: {len(result['objects'])}  MACs: {compute['macs']['total'] / 1e9:.3f} G "
          f"(detect {compute['macs']['detect'] / 1e9:.3f}, segment {compute['macs']['segment'] / 1e9:.3f})  "
          f"ROI voxels: {compute['roi_voxels']}  time: {compute['seconds']['total'] * 1e3:.0f} ms"
          f"{' (after a warm-up run)' if result['timed_after_warm_up'] else ' (first run: includes warm-up)'}  "
          f"runtime: {result['runtime']}")
    if result["png"]:
        print(f"picture: {result['png']}")
    return 0


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from models.checkpoint import load_pair
    from models.export.onnx_export import export_onnx

    detector, segmenter = load_pair(args.detector, args.segmenter)
    if args.int8:
        from models.export.export_cache import Int8Calibration
        from models.export.quantize import export_int8
        from pipelines.datasets.calibration import store_calibration

        profile = detector.profile
        methods = tuple(args.calibration_methods)
        calibration = (Int8Calibration.simulated(profile, frames=args.calibration_frames, methods=methods)
                       if args.calibration is None else
                       store_calibration(args.calibration, profile, frames=args.calibration_frames, methods=methods))
        manifest = export_int8(detector, segmenter, args.out, cubes=calibration.cubes,
                               calibration=calibration.description, methods=calibration.methods)
        quant = manifest["quantization"]
        agreement = ", ".join(f"{m} {a:.5f}" for m, a in quant["label_agreement_by_method"].items())
        print(f"int8 (QDQ), calibrated on {len(calibration.cubes)} {quant['calibration']['source']} frames; "
              f"ROI label agreement with float: {agreement}; kept {quant['method']}")
    else:
        manifest = export_onnx(detector, segmenter, args.out)
    for stage in ("detector", "segmenter"):
        graph = manifest[stage]
        inputs = ", ".join(f"{name} {tuple(v['shape'])}" for name, v in graph["inputs"].items())
        outputs = ", ".join(f"{name} {tuple(v['shape'])}" for name, v in graph["outputs"].items())
        print(f"{args.out}/{graph['file']}: {inputs} -> {outputs}")
    print(f"opset {manifest['opset']}, standard operators only, checked with onnx.checker; "
          f"manifest: {args.out}/manifest.json")
    return 0


def _cmd_export_recording(args: argparse.Namespace) -> int:
    from pipelines.recordings.export import export_recording

    result = export_recording(args.predictions, mcap=args.mcap, rrd=args.rrd, ros2=args.ros2, sequence=args.sequence,
                              limit=args.limit, log_power=args.log_power, overwrite=args.overwrite)
    for kind, out in result["outputs"].items():
        print(f"{out['path']}: {kind}, {out['frames']} frames, {out['bytes']} bytes in {out['seconds']:.2f} s")
    return 0


def _add_export_recording(export_sub: Any) -> None:
    """``radarseg export recording``."""
    recording = export_sub.add_parser("recording", help="a predictions store as recordings: MCAP for Foxglove, "
                                                        ".rrd for Rerun, MCAP of ROS 2 messages")
    recording.add_argument("predictions", help="predictions store (segment-batch --out)")
    recording.add_argument("--mcap", help="MCAP with Foxglove's schemas (points, objects, RA/RD label maps)")
    recording.add_argument("--rrd", help="Rerun recording")
    recording.add_argument("--ros2", help="MCAP of ROS 2 messages (radar_msgs/RadarTracks, sensor_msgs/PointCloud2)")
    recording.add_argument("--sequence", help="that sequence only (default: every sequence, one after the other)")
    recording.add_argument("--limit", type=int, help="the first LIMIT frames only")
    recording.add_argument("--no-log-power", dest="log_power", action="store_false",
                           help="do not read the predictions' source for log power (points and maps without it)")
    recording.add_argument("--overwrite", action="store_true", help="replace existing output files")
    recording.set_defaults(func=_cmd_export_recording)


def _cmd_models_summary(args: argparse.Namespace) -> int:
    import json

    from pipelines.evaluation.summary import SHIPPED, format_summary, models_summary

    rows = models_summary(tuple(args.profile or ()), tuple(args.checkpoint or SHIPPED))
    print(json.dumps(rows, indent=2) if args.json else format_summary(rows))
    return 0


def _served_model(args: argparse.Namespace) -> dict[str, str]:
    """The one model ``serve --detector D --segmenter S`` serves, named ``--model-name`` or after its radar."""
    import re
    from pathlib import Path

    from models.capabilities import Stage
    from models.checkpoint import load_checkpoint

    detector = load_checkpoint(args.detector, stage=Stage.DETECTOR, option="--detector")
    load_checkpoint(args.segmenter, stage=Stage.SEGMENTER, option="--segmenter")
    name = args.model_name or re.sub(r"[^a-z0-9_.-]+", "-", detector.profile.name.lower()).strip("-.")[:64] or "model"
    return {"name": name, "detector": str(Path(args.detector).absolute()),
            "segmenter": str(Path(args.segmenter).absolute()), "runtime": runtime_of(args)}


def _cmd_serve(args: argparse.Namespace) -> int:
    """Become ``python -m service`` (same pid, so whoever started us stops the server by it): the service's
    own runner binds the port before the models load and bounds request heads. By module name, so that pipelines
    never imports the service; its settings (RADARSEG_*) and their defaults are the service's."""
    import os

    argv = [sys.executable, "-m", "service", "--log-level", args.log_level]
    argv += [f"--{name}={getattr(args, name)}" for name in ("host", "port") if getattr(args, name) is not None]
    if (args.detector is None) != (args.segmenter is None):
        raise UserError("--detector and --segmenter go together (one served model), or neither (RADARSEG_MODELS)")
    if args.detector is not None:
        os.environ["RADARSEG_MODELS"] = json.dumps([_served_model(args)])
        os.environ.pop("RADARSEG_DEFAULT_MODEL", None)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(sys.executable, argv)
    return 1  # not reached


def _cmd_radar_show(args: argparse.Namespace) -> int:
    from radar.profiles import get_profile
    from radar.profiles.files import describe

    rows = describe(get_profile(args.profile))
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")
    return 0


def _cmd_radar_tune_growing(args: argparse.Namespace) -> int:
    import dataclasses

    from pipelines.progress import progress
    from radar.growing_sweep import BRIDGES, DISTANCES_M, FLOORS_DB, sweep_growing, write_settings

    with progress(total=len(DISTANCES_M) * len(FLOORS_DB) * len(BRIDGES), desc=f"sweep {args.profile}",
                  unit="setting") as bar:
        result = sweep_growing(args.profile, sequences=args.sequences, frames=args.frames, seed=args.seed,
                               target_recall=args.target_recall, progress=lambda done, total: bar.update(1))
    if args.write:
        if args.profile in BUILTIN_PRESETS:
            raise UserError(f"--write: {args.profile} is a built-in preset; copy its file and tune the copy")
        write_settings(args.profile, result)
    if args.json:
        print(json.dumps({**dataclasses.asdict(result), "settings": result.settings()}, indent=2))
        return 0
    print(f"{result.profile}: {result.frames} simulated frames, seeded at the true centres")
    print(f"{'distance m':>10} {'floor dB':>8} {'bridge':>6} {'recall':>6} {'ROI voxels':>10}")
    for row in sorted(result.rows, key=lambda r: (r.recall < result.target_recall, r.roi_voxels)):
        mark = "  <- chosen" if row == result.chosen else ""
        print(f"{row.distance_m:>10.1f} {row.min_snr_db:>8.1f} {row.bridge:>6d} {row.recall:>6.3f} "
              f"{row.roi_voxels:>10.0f}{mark}")
    if not result.reached:
        print(f"no setting reaches recall {result.target_recall}: the highest is chosen")
    where = f"written into {args.profile}" if args.write else "add to the profile file (or run with --write)"
    print(f"\n{where}:\n\n{result.toml()}")
    return 0


def _recorded_coupling(adc_path: str) -> bool | None:
    """Whether the ADC file inside a recording (``DIR/seq_*/adc/NNNNNN.npy``) carries TDM coupling, as its
    ``recording.json`` says; ``None`` for a file outside a recording."""
    from pathlib import Path

    meta_path = Path(adc_path).resolve().parent.parent.parent / "recording.json"
    if Path(adc_path).resolve().parent.name != "adc" or not meta_path.is_file():
        return None
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    return bool(meta.get("tdm_compensation", False)) if meta.get("content") == "adc" else None


def _cmd_process_adc(args: argparse.Namespace) -> int:
    import numpy as np

    from radar.adc import adc_shape, layout_hint, process_adc
    from radar.errors import DataError
    from radar.io.npy import load_npy, read_npy_header
    from radar.profiles import get_profile

    if args.adc.endswith(".bin"):  # a TI capture file
        from pipelines.ti_commands import process_capture

        return process_capture(args)
    profile = get_profile(args.profile)
    what, expected = f"ADC samples ({args.layout} layout)", adc_shape(profile, args.layout)
    found = read_npy_header(args.adc, what=what).shape  # checked before the data is read (a 16 GiB header was read)
    if found != expected:
        raise DataError(args.adc, f"ADC samples of profile {profile.name!r} in layout {args.layout!r} have shape "
                                  f"{expected}, got {found}{layout_hint(found, profile, args.layout)}")
    adc = load_npy(args.adc, shape=expected, dtypes=(np.complexfloating,), what=what)
    recorded = _recorded_coupling(args.adc)
    coupled = {"tdm": True, "none": False, "auto": True if recorded is None else recorded}[args.coupling]
    cube = process_adc(adc, profile, layout=args.layout, tdm_compensation=coupled)
    np.save(args.out, cube, allow_pickle=False)
    source = "" if args.coupling != "auto" or recorded is None else ", as its recording.json says"
    print(f"RAD cube {cube.shape} {cube.dtype} written to {args.out} "
          f"(TDM coupling {'compensated' if coupled else 'none to compensate'}{source})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="radarseg", description="ERASE-Net radar semantic segmentation")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--version", action="version", version=f"radarseg {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_data_commands(sub)
    _add_frame_commands(sub)
    from radar.ti.capture_command import add_capture_parser

    add_capture_parser(sub)
    _add_model_commands(sub)
    return with_defaults_shown(parser)


def _add_data_commands(sub: Any) -> None:
    """simulate, the jobs, prune, store."""
    sim = sub.add_parser("simulate", help="simulate a labelled recording with the FMCW scene simulator")
    add_radar_option(sim, former=True, default="small")
    sim.add_argument("--sequences", type=int, default=2, help="sequences (scenes) to simulate")
    sim.add_argument("--frames", type=int, default=8, help="frames per sequence")
    sim.add_argument("--seed", type=int, default=0, help="seed of the scenes and the noise")
    sim.add_argument("--out", required=True, help="output directory (must not hold a recording yet)")
    sim.add_argument("--adc", action="store_true", help="store raw ADC samples instead of RAD cubes")
    sim.add_argument("--format", choices=("npy", "dca1000"), default="npy",
                     help="--adc: a .npy per frame, or a DCA1000 capture (adc_data.bin) per sequence")
    sim.set_defaults(func=_cmd_simulate)

    for name, job in JOBS.items():  # parsed by the job's own parser (see main)
        sub.add_parser(name, add_help=False, help=job.help)

    prune = sub.add_parser("prune", help="network slimming: remove the channels with the smallest BatchNorm "
                                         "scales, save a genuinely narrower checkpoint")
    prune.add_argument("--checkpoint", required=True, help="checkpoint to prune (ideally trained with --slim-lambda)")
    budget = prune.add_mutually_exclusive_group(required=True)
    budget.add_argument("--ratio", type=float, help="fraction of BatchNorm channels removed (global threshold)")
    budget.add_argument("--params", type=int, help="or: largest parameter count of the pruned model")
    budget.add_argument("--macs", type=int, help="or: largest MACs per frame (dense models: detector, baselines)")
    prune.add_argument("--min-channels", type=int, default=1, help="channels every layer keeps at least")
    prune.add_argument("--out", required=True, help="pruned checkpoint")
    prune.add_argument("--half", action=argparse.BooleanOptionalAction, default=None,
                       help="store the weights in float16 (half the size on disk, as `train export` does); "
                            "default: float16 when the input is stored in float16, else float32 (to fine-tune)")
    prune.set_defaults(func=_cmd_prune)
    store = sub.add_parser("store", help="inspect a preprocessed store")
    store_sub = store.add_subparsers(dest="store_command", required=True)
    info = store_sub.add_parser("info", help="frames per split, class counts, statistics, quarantined frames; of a "
                                             "predictions store: frames, class voxels, detections per frame")
    info.add_argument("store", help="store path")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.set_defaults(func=_cmd_store_info)


def _add_frame_commands(sub: Any) -> None:
    """segment, radar, process-adc: one frame or one profile."""
    seg = sub.add_parser("segment", help="run ERASE-Net on one .npy cube and print objects and compute")
    seg.add_argument("cube", help=".npy file: RAD cube (R, A, D) of the checkpoint's preset (or ADC samples with "
                                  "--input adc)")
    seg.add_argument("--detector", required=True, help="detector checkpoint")
    seg.add_argument("--segmenter", required=True, help="segmenter checkpoint")
    seg.add_argument("--input", choices=[kind.value for kind in InputKind], default=None,
                     help="what the cube holds: complex (RAD), magnitude (|I|, linear), log_power "
                          "(10 log10(|I|^2 + 1) dB), adc (raw samples); a complex cube is complex unless said, a "
                          "real-valued one must say it (docs/design.md section 2)")
    seg.add_argument("--log-power", dest="input", action="store_const", const=InputKind.log_power.value,
                     help="the same as --input log_power")
    seg.add_argument("--score-threshold", type=float, default=SCORE_THRESHOLD, help="detector score threshold")
    seg.add_argument("--png", help="write RA/RD pictures with the prediction here")
    add_runtime_option(seg)
    seg.add_argument("--no-warm-up", dest="warm_up", action="store_false",
                     help="report the first run's time (by default the cube is segmented once before the timed run, "
                          "so the time is a steady frame's)")
    seg.add_argument("--json", action="store_true", help="print the result as JSON (for machines)")
    seg.set_defaults(func=_cmd_segment)

    export = sub.add_parser("export", help="export the models for other runtimes (`train export` writes a "
                                           "shippable checkpoint)")
    export_sub = export.add_subparsers(dest="export_command", required=True)
    onnx = export_sub.add_parser("onnx", help="detector.onnx and segmenter.onnx (standard ONNX operators, for "
                                              "ONNX Runtime, OpenVINO, TensorRT, ...) and manifest.json")
    onnx.add_argument("--detector", required=True, help="detector checkpoint")
    onnx.add_argument("--segmenter", required=True, help="segmenter checkpoint (MinkUNet)")
    onnx.add_argument("--out", required=True, help="output directory")
    onnx.add_argument("--int8", action="store_true",
                      help="also quantise both graphs (onnxruntime static quantisation, QDQ, int8 weights per "
                           "channel); the float graphs go to OUT/float")
    onnx.add_argument("--calibration", metavar="STORE",
                      help="--int8: calibrate on the train split of this store (default: simulated frames of the "
                           "checkpoints' preset)")
    onnx.add_argument("--calibration-frames", type=int, default=8, metavar="N", help="--int8: frames (default 8)")
    onnx.add_argument("--calibration-methods", nargs="+", choices=("MinMax", "Entropy", "Percentile"),
                      default=["MinMax", "Entropy", "Percentile"],
                      help="--int8: methods tried; the best ROI label agreement with float is kept (default: all)")
    onnx.set_defaults(func=_cmd_export_onnx)
    _add_export_recording(export_sub)

    radar_cmd = sub.add_parser("radar", help="radar profiles")
    radar_sub = radar_cmd.add_subparsers(dest="radar_command", required=True)
    show = radar_sub.add_parser("show", help="print what a profile derives (bins, resolutions, limits)")
    show.add_argument("profile", help=RADAR_HELP)
    show.set_defaults(func=_cmd_radar_show)
    tune = radar_sub.add_parser("tune-growing", help="derive a radar's region-growing settings from a sweep on its "
                                                     "simulated frames (prints the profile file's table)")
    tune.add_argument("profile", help=RADAR_HELP)
    tune.add_argument("--sequences", type=int, default=6, help="simulated sequences")
    tune.add_argument("--frames", type=int, default=2, help="frames per sequence")
    tune.add_argument("--seed", type=int, default=0, help="scene seed")
    tune.add_argument("--target-recall", type=float, default=0.95,
                      help="recall from the true centres the settings must reach (then the most compact ROI)")
    tune.add_argument("--write", action="store_true", help="write the chosen settings into the profile file")
    tune.add_argument("--json", action="store_true", help="print the sweep as JSON")
    tune.set_defaults(func=_cmd_radar_tune_growing)
    from pipelines.ti_commands import add_from_ti_parser

    add_from_ti_parser(radar_sub)

    _add_process_adc_command(sub)


def _add_process_adc_command(sub: Any) -> None:
    """process-adc: one frame of ADC samples (.npy, or a TI capture .bin) into a RAD cube."""
    adc = sub.add_parser("process-adc", help="raw complex ADC samples of one frame -> RAD cube (.npy)")
    adc.add_argument("adc", help=".npy of complex ADC samples, or a capture (.bin: DCA1000 adc_data.bin, mmWave "
                                 "Studio PREFIX_Raw_0.bin) read with the profile's [capture] settings")
    add_radar_option(adc, required=True)
    adc.add_argument("--layout", choices=["sck", "ti"], default="sck",
                     help="sck: (sample, chirp, virtual element); ti: TX-interleaved (chirp, rx, sample)")
    adc.add_argument("--coupling", choices=["auto", "tdm", "none"], default="auto",
                     help="TDM Doppler-angle coupling in the samples: tdm (what a TDM-MIMO radar records; "
                          "compensated), none (not compensated), auto (default: what the recording.json of a "
                          "file inside a recording says, else tdm)")
    adc.add_argument("--no-tdm-compensation", dest="coupling", action="store_const", const="none",
                     help="the same as --coupling none")
    adc.add_argument("--out", required=True, help="output .npy (complex64 (R, A, D))")
    from pipelines.ti_commands import add_capture_options

    add_capture_options(adc)
    adc.set_defaults(func=_cmd_process_adc)


def _add_model_commands(sub: Any) -> None:
    """upload-check, models, serve, demo."""
    upload = sub.add_parser("upload-check", help="what `ray job submit --working-dir DIR` would upload; a one-line "
                                                 "error over Ray's limit (HTTP 413) naming the largest files")
    from pipelines import upload_check

    upload_check.add_arguments(upload)
    upload.set_defaults(func=upload_check.run)

    models = sub.add_parser("models", help="describe the models")
    models_sub = models.add_subparsers(dest="models_command", required=True)
    summary = models_sub.add_parser("summary", help="params and MACs of the shipped models (or --checkpoint), "
                                                    "and of the full-size models per --profile")
    summary.add_argument("--checkpoint", action="append",
                         help="a detector or segmenter checkpoint instead of the shipped ones; repeat for several")
    add_radar_option(summary, former=True, append=True, choices=sorted(BUILTIN_PRESETS),
                     help="also the registry's full-size models for this preset; repeat for several")
    summary.add_argument("--json", action="store_true", help="print the rows as JSON (for machines)")
    summary.set_defaults(func=_cmd_models_summary)

    serve = sub.add_parser("serve", help="run the HTTP segmentation service (uvicorn; settings from RADARSEG_*)")
    serve.add_argument("--host", help="bind address (default 127.0.0.1, or RADARSEG_HOST)")
    serve.add_argument("--port", type=int, help="port (default 8000, or RADARSEG_PORT)")
    serve.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                       help="uvicorn's log level")
    serve.add_argument("--detector", help="serve this one pair (with --segmenter) instead of RADARSEG_MODELS")
    serve.add_argument("--segmenter", help="the pair's segmenter checkpoint")
    serve.add_argument("--model-name", help="the pair's model name (default: its radar's name)")
    add_runtime_option(serve, "what runs the pair (with --detector and --segmenter; RADARSEG_MODELS gives each "
                              "model's \"runtime\"): torch (default), torch-int8, onnx or onnx-int8")
    serve.set_defaults(func=_cmd_serve)

    demo = sub.add_parser("demo", help="run the end-to-end demo on embedded defaults")
    demo.add_argument("--out", default="out/demo", help="directory for the recording, store, report and "
                                                            "pictures")
    demo.set_defaults(func=_cmd_demo)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("radarseg")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def _command_index(argv: list[str]) -> int | None:
    """Position of the command in ``argv`` (the first word that is not a top-level option)."""
    return next((i for i, word in enumerate(argv) if not word.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    at = _command_index(argv)
    command = argv[at] if at is not None else None
    verbose = "-v" in argv[:at] or "--verbose" in argv[:at]
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if command in JOBS:  # a job: its own parser reads the rest (pipelines.jobs)
        try:
            job = JOBS[command]
            _, summary = run_job(job.module, argv[at + 1:], prog=f"radarseg {command}", options=job.options)
        except USER_ERRORS as exc:
            return report_error(f"radarseg {command}", exc)
        print(summary)
        return 0
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except USER_ERRORS as exc:
        return report_error(f"radarseg {args.command}", exc)


if __name__ == "__main__":
    sys.exit(main())
