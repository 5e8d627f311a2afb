"""``radarseg segment``, ``export onnx|recording`` and ``process-adc``: one frame through the pair, the pair or
a predictions store for other tools, one frame of ADC samples into a cube."""

from __future__ import annotations

import argparse
import json
from typing import Any

from pipelines.radar_option import add_radar_option
from pipelines.runtime_option import add_runtime_option, runtime_of
from radar.centres import SCORE_THRESHOLD
from radar.input_kind import InputKind


def add_commands(sub: Any) -> None:
    """segment, export, process-adc: one frame, or the models for other runtimes."""
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


def _cmd_export_recording(args: argparse.Namespace) -> int:
    from pipelines.recordings.export import export_recording

    result = export_recording(args.predictions, mcap=args.mcap, rrd=args.rrd, ros2=args.ros2, sequence=args.sequence,
                              limit=args.limit, log_power=args.log_power, overwrite=args.overwrite)
    for kind, out in result["outputs"].items():
        print(f"{out['path']}: {kind}, {out['frames']} frames, {out['bytes']} bytes in {out['seconds']:.2f} s")
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
