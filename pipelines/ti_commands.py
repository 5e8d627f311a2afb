"""TI captures on the command line: ``process-adc CAPTURE.bin`` and ``simulate --adc --format dca1000``
(:mod:`pipelines.cli.frame_commands` and :mod:`pipelines.cli.data_commands` call these)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from radar.errors import UserError

CAPTURE_SUFFIX = ".bin"


def add_capture_options(adc_parser: argparse.ArgumentParser) -> None:
    """process-adc's options for a capture file (.bin); the profile's [capture] table gives their defaults."""
    group = adc_parser.add_argument_group("capture files (.bin: a DCA1000 adc_data.bin or mmWave Studio's "
                                          "PREFIX_Raw_0.bin)")
    group.add_argument("--frame", type=int, default=0, help="which frame of the capture (default 0)")
    group.add_argument("--lvds-lanes", type=int, choices=(2, 4), help="LVDS lanes (default: the profile's [capture])")
    group.add_argument("--iq-order", choices=("iq", "qi"), help="I/Q order of the words (default: the profile's)")
    group.add_argument("--offset-binary", action="store_true", default=None,
                       help="words are unsigned with 0 at 32768 (default: the profile's)")
    group.add_argument("--skip-partial", action="store_true",
                       help="read the whole frames of a capture that stopped mid-frame (refused otherwise)")


def capture_format_of(args: argparse.Namespace, profile):
    from radar.ti.dca1000 import CaptureFormat

    try:
        return CaptureFormat.of_profile(profile, lvds_lanes=args.lvds_lanes, iq_order=args.iq_order,
                                        offset_binary=args.offset_binary)
    except ValueError as exc:
        raise UserError(f"{args.profile}: [capture] {exc}") from None


def process_capture(args: argparse.Namespace) -> int:
    """``process-adc CAPTURE.bin --profile P --out CUBE.npy [--frame N]``: one frame of a capture into a RAD cube."""
    from radar.adc import process_adc
    from radar.profiles import get_profile
    from radar.ti.capture import Capture

    profile = get_profile(args.profile)
    capture = Capture(args.adc, profile, capture_format_of(args, profile),
                      partial="skip" if args.skip_partial else "refuse")
    frame = capture.frame(args.frame)
    coupled = args.coupling != "none"  # a TDM-MIMO radar's capture carries the coupling
    cube = process_adc(frame, profile, layout="ti", tdm_compensation=coupled)
    np.save(args.out, cube, allow_pickle=False)
    lost = f"; {capture.lost_bytes} bytes of lost packets read as zero" if capture.lost_bytes else ""
    print(f"frame {args.frame} of {len(capture)} ({capture.format.describe()}) -> RAD cube {cube.shape} {cube.dtype} "
          f"written to {args.out} (TDM coupling {'compensated' if coupled else 'none to compensate'}){lost}")
    if capture.lost_bytes:
        print(f"warning: {args.adc}: frame {args.frame} lost {capture.lost_bytes} bytes (zero-filled)", file=sys.stderr)
    return 0


def simulate_capture_recording(*, preset: str, sequences: int, frames: int, seed: int, out: str) -> Path:
    """``simulate --adc --format dca1000``: a labelled ADC recording whose sequences are DCA1000 captures."""
    from radar.io.recording import RecordingWriter
    from radar.profiles import get_profile
    from radar.simulate import SimulatorConfig, simulate_sequence

    if sequences < 1 or frames < 1:
        raise UserError(f"sequences and frames must be >= 1, got {sequences} and {frames}")
    profile = get_profile(preset)
    config = SimulatorConfig()
    source = {"kind": "sim", "seed": seed, "simulator": config.stamp()}
    with RecordingWriter(out, profile, source=source, content="adc", adc_format="dca1000") as writer:
        for s in range(sequences):
            for frame in simulate_sequence(profile, frames, seed=seed, sequence_index=s, config=config):
                writer.write(frame)
    if writer.capture.clipped:
        print(f"warning: {writer.capture.clipped} samples clipped to the ADC's range", file=sys.stderr)
    return Path(out)
