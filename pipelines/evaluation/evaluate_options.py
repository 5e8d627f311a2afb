"""The evaluate job's options and its config (:mod:`pipelines.evaluation.evaluate` is the job): light on purpose,
no torch, so that ``radarseg evaluate --help`` and a wrong option answer at once."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from models.runtime import Runtime
from pipelines.evaluation.tracker_comparison import TRACKERS, parse_trackers
from pipelines.jobs import always, cap, field_defaults, smoke
from pipelines.runtime_option import add_runtime_option, runtime_of
from radar.centres import SCORE_THRESHOLD

D_THRESH_SWEEP_M = (4.0, 6.0, 8.0, 10.0, 12.0, 14.0)


@dataclass(frozen=True)
class EvaluateConfig:
    detector: str
    segmenter: str
    store: str
    out: str
    split: str | None = "test"  # None: every frame of the store
    max_frames: int = smoke(0, cap(2, fill=True))  # 0 = every frame of the split
    pictures: int = smoke(4, cap(1))
    sweep: tuple[float, ...] = D_THRESH_SWEEP_M
    sweep_frames: int = smoke(48, cap(2))
    score_threshold: float | None = None  # operating threshold (None = EraseNet's default)
    oracle: bool = True  # also segment from true centres
    doppler_refinement: bool = True  # refine the detector's Doppler from the cube (radar.doppler), as EraseNet does
    device: str = "cpu"  # the torch runtime's device
    runtime: str = "torch"  # the runtime scored (models.runtime.RUNTIMES)
    onnx_dir: str | None = None  # the ONNX runtimes: this export instead of the cached one
    threads: int = smoke(0, always(1))  # torch intra-op threads (0 = torch's default); per-stage seconds with these
    progress: bool = True
    single_cube: bool = False  # a detector that reads earlier frames sees each frame alone (no history)
    trackers: tuple[str, ...] = ()  # also compare these trackers on the same objects (tracker_comparison.TRACKERS)
    track_priors: float | None = None  # seed from confirmed tracks' predictions down to this score (radar.track_priors)
    track_priors_gate_m: float = 3.0  # how near a track's prediction it must be (radar.track_priors.PRIOR_GATE_M)

    def __post_init__(self) -> None:
        if self.max_frames < 0 or self.pictures < 0 or self.sweep_frames < 0:
            raise ValueError("max_frames, pictures and sweep_frames must be >= 0")
        if any(d <= 0 for d in self.sweep):
            raise ValueError(f"sweep distances must be > 0 m, got {self.sweep}")
        Runtime.parse(self.runtime)
        if unknown := [name for name in self.trackers if name not in TRACKERS]:
            raise ValueError(f"trackers must be among {tuple(TRACKERS)}, got {unknown}")
        if self.track_priors is not None and not 0 < self.track_priors < 1:
            raise ValueError(f"track_priors must be a score in (0, 1), got {self.track_priors}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = field_defaults(EvaluateConfig)
    parser.add_argument("--detector", required=True, help="detector checkpoint")
    parser.add_argument("--segmenter", required=True, help="segmenter checkpoint")
    parser.add_argument("--store", required=True, help="preprocessed store (radarseg preprocess)")
    parser.add_argument("--split", default=defaults.split, help="train, val, test, or 'all'")
    parser.add_argument("--out", required=True, help="output directory (metrics.json, report.md, pictures)")
    parser.add_argument("--max-frames", type=int, default=defaults.max_frames,
                        help="evaluate this many frames, evenly spread (0: all)")
    parser.add_argument("--pictures", type=int, default=defaults.pictures, help="frames drawn (truth above prediction)")
    parser.add_argument("--sweep", type=float, nargs="+", default=list(D_THRESH_SWEEP_M), help="D_thresh values (m)")
    parser.add_argument("--sweep-frames", type=int, default=defaults.sweep_frames,
                        help="frames of the region-growing D_thresh sweep")
    parser.add_argument("--score-threshold", type=float, help=f"detector score threshold (default: {SCORE_THRESHOLD})")
    parser.add_argument("--no-oracle", action="store_true", help="skip segmentation from true centres")
    parser.add_argument("--no-doppler-refinement", action="store_true",
                        help="keep the detector's own Doppler (no refinement from the cube)")
    parser.add_argument("--device", default=defaults.device, help="torch device (cpu, cuda)")
    add_runtime_option(parser, "the runtime scored: torch (default), torch-int8 (the segmenter in the int8 sparse "
                               "kernels, calibrated on the store's train split, simulated frames of the preset if it "
                               "has none), onnx or onnx-int8 (the export cached on first use)")
    parser.add_argument("--threads", type=int, default=defaults.threads,
                        help="torch threads (0: torch's default; 1 is faster when other jobs share the CPU)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--single-cube", action="store_true",
                        help="a detector that reads earlier frames of the sequence sees each frame alone")
    parser.add_argument("--trackers", type=parse_trackers, default=defaults.trackers,
                        help=f"also run these trackers on the same objects and score them with GOSPA, HOTA, MOTA, "
                             f"IDF1 and velocity error (comma-separated: {','.join(TRACKERS)}; Stone Soup's and "
                             f"HOTA need the 'tracking' extra)")
    parser.add_argument("--track-priors", type=float, metavar="SCORE", default=defaults.track_priors,
                        help="where a confirmed track's predicted position has no detection, seed region growing "
                             "from the detector's best centre near it scored at least SCORE (below the operating "
                             "score); the segmenter decides. Off by default")
    parser.add_argument("--track-priors-gate", type=float, metavar="METRES", default=defaults.track_priors_gate_m,
                        help="with --track-priors: how near a track's predicted position the centre must be (m)")


def config_from_args(args: argparse.Namespace) -> EvaluateConfig:
    return EvaluateConfig(detector=args.detector, segmenter=args.segmenter, store=args.store, out=args.out,
                          split=None if args.split == "all" else args.split, max_frames=args.max_frames,
                          pictures=args.pictures,
                          sweep=tuple(args.sweep), sweep_frames=args.sweep_frames,
                          score_threshold=args.score_threshold, oracle=not args.no_oracle,
                          doppler_refinement=not args.no_doppler_refinement, device=args.device,
                          runtime=runtime_of(args),
                          threads=args.threads, progress=not args.no_progress, single_cube=args.single_cube,
                          trackers=tuple(args.trackers), track_priors=args.track_priors,
                          track_priors_gate_m=args.track_priors_gate)
