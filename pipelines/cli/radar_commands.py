"""``radarseg radar show|tune-growing|from-ti``: what a radar profile derives, its region-growing settings, a
profile from a TI .cfg."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from pipelines.radar_option import RADAR_HELP
from radar.errors import UserError
from radar.profiles import BUILTIN_PRESETS


def add_commands(sub: Any) -> None:
    """radar show, tune-growing and from-ti: a radar profile."""
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
    _add_from_ti(radar_sub)


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


def _add_from_ti(radar_sub: Any) -> None:
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
    cmd.set_defaults(func=_cmd_from_ti)


def _cmd_from_ti(args: argparse.Namespace) -> int:
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
