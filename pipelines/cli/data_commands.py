"""``radarseg simulate``, ``prune`` and ``store info``: a recording, a narrower checkpoint, a store described."""

from __future__ import annotations

import argparse
import json
from typing import Any

from pipelines.radar_option import add_radar_option
from radar.errors import UserError


def add_commands(sub: Any) -> None:
    """simulate, prune, store info."""
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
