"""The compare job's options, its config and the models it compares (:mod:`pipelines.evaluation.compare` is the
job): light on purpose, no torch, so that ``radarseg compare --help`` and a wrong option answer at once."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from enum import StrEnum

from pipelines.jobs import always, cap, field_defaults, smoke


class Entry(StrEnum):
    """What a row of the comparison is (its ``kind`` in compare.json) and the checkpoints it takes."""

    ERASENET = "erasenet"  # (detector, segmenter)
    CFAR = "cfar"  # (segmenter,): CFAR seeds in place of the detector
    BASELINE = "baseline"  # (multi-view network,) or a U-Net pair


KINDS = tuple(Entry)
CHECKPOINTS_TAKEN = {Entry.ERASENET: (2,), Entry.CFAR: (1,), Entry.BASELINE: (1, 2)}
CFAR_NAME = "CFAR + ERASE-Net segmenter"


@dataclass(frozen=True)
class ModelSpec:
    """One row of the comparison: a display name, what it is and its checkpoint files.

    ``erasenet``: (detector, segmenter); ``cfar``: (segmenter,); ``baseline``: (multi-view network,) or
    two single-view U-Nets (RD and RA, either order)."""

    name: str
    kind: Entry
    checkpoints: tuple[str, ...]

    def __post_init__(self) -> None:
        if not self.name.strip():
            raise ValueError("a model needs a non-empty name")
        if self.kind not in KINDS:
            raise ValueError(f"model kind must be one of {[str(k) for k in KINDS]}, got {self.kind!r}")
        object.__setattr__(self, "kind", Entry(self.kind))
        expected = CHECKPOINTS_TAKEN[self.kind]
        if len(self.checkpoints) not in expected or not all(self.checkpoints):
            raise ValueError(f"{self.name!r}: a {self.kind} model takes {' or '.join(map(str, expected))} "
                             f"checkpoint(s), got {list(self.checkpoints)}")


def parse_model(text: str, kind: Entry, *, default_name: str | None = None) -> ModelSpec:
    """``"NAME=CKPT[,CKPT]"`` as a :class:`ModelSpec` (``NAME=`` may be left out when ``default_name`` is given)."""
    name, sep, paths = text.partition("=")
    if not sep:
        if default_name is None:
            raise ValueError(f"expected NAME=CHECKPOINT[,CHECKPOINT] (e.g. \"TMVA-Net=tmva.pt\"), got {text!r}")
        name, paths = default_name, text
    name = name.strip()
    if not name:
        raise ValueError(f"expected a model name before '=' in {text!r}")
    checkpoints = tuple(p.strip() for p in paths.split(","))
    if not all(checkpoints):
        raise ValueError(f"expected comma-separated checkpoint paths after '=' in {text!r}")
    return ModelSpec(name, kind, checkpoints)


@dataclass(frozen=True)
class CompareConfig:
    store: str
    out: str
    models: tuple[ModelSpec, ...]
    split: str | None = "test"  # None: every frame of the store
    max_frames: int = smoke(0, cap(2, fill=True))  # 0 = every usable frame of the split
    pictures: int = smoke(3, cap(1))
    score_threshold: float | None = None  # ERASE-Net centre score threshold (None = EraseNet's default)
    threads: int = smoke(1, always(1))
    device: str = "cpu"
    progress: bool = True
    command: str = ""  # recorded in the report

    def __post_init__(self) -> None:
        if not self.models:
            raise ValueError("give at least one model (--erasenet, --baseline or --cfar-segmenter)")
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must differ, got {names}")
        if self.max_frames < 0 or self.pictures < 0 or self.threads < 1:
            raise ValueError(f"max_frames and pictures must be >= 0 and threads >= 1, got {self.max_frames}, "
                             f"{self.pictures}, {self.threads}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = field_defaults(CompareConfig)
    parser.add_argument("--store", required=True, help="preprocessed store (radarseg preprocess)")
    parser.add_argument("--split", default=defaults.split, help="train, val, test, or 'all'")
    parser.add_argument("--out", required=True, help="output directory (compare.json, compare.md, compare_frames.png)")
    parser.add_argument("--erasenet", action="append", default=[], metavar="NAME=DETECTOR,SEGMENTER",
                        help="an ERASE-Net, e.g. 'ERASE-Net (M)=checkpoints/detector.pt,checkpoints/segmenter.pt'")
    parser.add_argument("--baseline", action="append", default=[], metavar="NAME=CKPT[,CKPT]",
                        help="TMVA-Net / SMVA-Net checkpoint, or a U-Net pair 'U-Net=unet_rd.pt,unet_ra.pt'")
    parser.add_argument("--cfar-segmenter", metavar="[NAME=]SEGMENTER",
                        help=f"CFAR + region growing + this segmenter (default name {CFAR_NAME!r})")
    parser.add_argument("--max-frames", type=int, default=defaults.max_frames,
                        help="score this many frames, evenly spread (0: all)")
    parser.add_argument("--pictures", type=int, default=defaults.pictures, help="frames in compare_frames.png")
    parser.add_argument("--score-threshold", type=float, help="ERASE-Net centre score threshold")
    parser.add_argument("--threads", type=int, default=defaults.threads,
                        help="torch threads (timings are taken with these)")
    parser.add_argument("--device", default=defaults.device, help="torch device (cpu, cuda)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def config_from_args(args: argparse.Namespace) -> CompareConfig:
    models = [parse_model(text, Entry.ERASENET) for text in args.erasenet]
    models += [parse_model(text, Entry.BASELINE) for text in args.baseline]
    if args.cfar_segmenter:
        models.append(parse_model(args.cfar_segmenter, Entry.CFAR, default_name=CFAR_NAME))
    return CompareConfig(store=args.store, out=args.out, models=tuple(models),
                         split=None if args.split == "all" else args.split, max_frames=args.max_frames,
                         pictures=args.pictures, score_threshold=args.score_threshold, threads=args.threads,
                         device=args.device, progress=not args.no_progress,
                         command=getattr(args, "command_line", ""))
