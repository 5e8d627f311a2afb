"""The command-line side of TI radars: ``radarseg radar from-ti``, ``process-adc CAPTURE.bin`` and
``simulate --adc --format dca1000`` (pipelines/cli.py registers the parsers here and calls these handlers)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from radar.errors import UserError

CAPTURE_SUFFIX = ".bin"


def add_from_ti_parser(radar_sub: Any) -> None:
    """``radarseg radar from-ti CONFIG.cfg --out PROFILE.toml``."""
    from radar.ti.boards import BOARDS

    cmd = radar_sub.add_parser("from-ti", help="a radar profile file from a TI mmWave SDK configuration (.cfg)")
    cmd.add_argument("config", help="the .cfg the radar was configured with (mmWave SDK CLI commands)")
    cmd.add_argument("--out", required=True, help="profile file to write (.toml)")
    cmd.add_argument("--name", help="the radar's name (default: the .cfg's file name)")
    cmd.add_argument("--angle-bins", type=int, help="angle FFT size (default: 64, or the next power of two that holds "
                                                    "the virtual array)")
    cmd.add_argument("--board", help=f"evaluation board, for the antenna positions: {', '.join(sorted(BOARDS))}, "
                                     f"each also spelled with awr or iwr for xwr (awr1843boost = xwr1843boost); "
                                     f"default: none stated, a uniform line")
    cmd.add_argument("--lvds-lanes", type=int, choices=(2, 4), default=2,
                     help="LVDS lanes of the DCA1000 capture: 2 (xWR16xx/18xx/68xx), 4 (xWR12xx/14xx)")
    cmd.add_argument("--no-scene", dest="scene", action="store_false",
                     help="write no [scene] table (by default a radar that sees less than 50 m gets rooms at its "
                          "scale: 1 to 3 people walking; docs/guides/indoor-scenes.md)")
    cmd.set_defaults(func=cmd_from_ti)


def cmd_from_ti(args: argparse.Namespace) -> int:
    from radar.profiles.files import describe
    from radar.ti.cfg import load_cfg
    from radar.ti.convert import ti_figures, write_profile

    cfg = load_cfg(args.config)
    if args.angle_bins is not None and args.angle_bins <= 0:
        raise UserError(f"--angle-bins must be > 0, got {args.angle_bins}")
    name = args.name or Path(args.config).stem
    profile = write_profile(cfg, args.out, source=Path(args.config).name, name=name, angle_bins=args.angle_bins,
                            board=args.board, lvds_lanes=args.lvds_lanes, scene=args.scene)
    print(f"profile {name!r} written to {args.out}: {profile.n_tx} TX (TX{', TX'.join(map(str, cfg.tx_fired))} in "
          f"firing order) x {profile.n_rx} RX, {cfg.adc_format} {cfg.adc_bits}-bit ADC")
    figures = ti_figures(cfg)
    print(f"TI's figures (c = 3e8): range resolution {figures['range_resolution_m']:.4f} m, max range "
          f"{figures['max_range_m']:.2f} m, velocity resolution {figures['velocity_resolution_mps']:.4f} m/s, max "
          f"velocity {figures['max_velocity_mps']:.2f} m/s")
    if cfg.ignored:
        print(f"ignored (processing chain, monitors): {' '.join(cfg.ignored)}")
    if cfg.unknown:
        print(f"unknown commands, ignored: {' '.join(cfg.unknown)}")
    for note in cfg.notes:
        print(f"note: {note}")
    scene = profile.extra.get("scene")
    if scene is not None:
        (person, (fewest, most)), = scene.classes
        print(f"scene: rooms at the radar's scale, {fewest} to {most} {person}s at {scene.range_m[0]:g} to "
              f"{scene.range_m[1]:g} m ([scene]; --no-scene for road scenes)")
    rows = dict(describe(profile))
    print(f"cube {rows['cube (R x A x D)']}; radarseg radar show {args.out} prints the rest")
    return 0


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
