"""A detector's operating point, written into its checkpoint: its heatmap logits shifted so that the product's one
score threshold (:data:`radar.centres.SCORE_THRESHOLD`, 0.3) keeps exactly the centres that a chosen score kept::

    python -m pipelines.training.operating_point DETECTOR.pt TUNED.pt --score 0.1

Every consumer of a detector (``radarseg segment``, ``evaluate``, the service, the ONNX and int8 exports) decodes
centres at that one threshold. A detector whose scores come out lower than the threshold expects (the ``carrada``
detector trained on windows: its true centres score 0.1-0.3 on whole frames) would keep too few centres to grow
regions from. Adding ``logit(threshold) - logit(score)`` to the bias of the heatmap's last convolution moves every
score monotonically: a cell scores at least the threshold after the shift exactly when it scored at least ``score``
before. Rankings, and so detection AP, are unchanged; only which centres pass changes, with no change anywhere the
detector runs. ``extra["operating_point"]`` records the score and the shift (``total`` with any earlier shift).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

from models.capabilities import Stage
from models.checkpoint import load_checkpoint, save_checkpoint
from pipelines.jobs import run_module
from radar.centres import SCORE_THRESHOLD
from radar.errors import UserError


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def heatmap_shift(score: float, threshold: float = SCORE_THRESHOLD) -> float:
    """The logit shift that maps a heatmap score of ``score`` onto ``threshold``."""
    if not 0.0 < score < 1.0:
        raise UserError(f"--score must be a heatmap score in (0, 1), got {score}")
    return logit(threshold) - logit(score)


def write_operating_point(source: str | Path, target: str | Path, score: float) -> dict[str, Any]:
    """A copy of the detector checkpoint ``source`` whose centres at the product's threshold are those of ``source``
    at ``score``; returns the record written to ``extra["operating_point"]``."""
    checkpoint = load_checkpoint(source, stage=Stage.DETECTOR, option="SOURCE")
    shift = heatmap_shift(score)
    branch = checkpoint.build().head.heatmap
    key = f"head.heatmap.{len(branch) - 1}.bias"
    if getattr(branch[-1], "bias", None) is None or key not in checkpoint.state_dict:
        raise UserError(f"{source}: the heatmap's last layer has no bias to shift")
    state = dict(checkpoint.state_dict)
    bias = state[key]
    state[key] = (bias.float() + shift).to(bias.dtype)
    earlier = checkpoint.extra.get("operating_point", {}).get("total_shift", 0.0)
    record = {"score": score, "threshold": SCORE_THRESHOLD, "shift": shift, "total_shift": earlier + shift}
    save_checkpoint(dataclasses.replace(checkpoint, state_dict=state,
                                        extra={**checkpoint.extra, "operating_point": record}), target)
    return record


@dataclasses.dataclass(frozen=True)
class OperatingPointConfig:
    """``python -m pipelines.training.operating_point SOURCE TARGET --score S``."""

    source: str
    target: str
    score: float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="detector checkpoint")
    parser.add_argument("target", help="the copy to write, its heatmap shifted")
    parser.add_argument("--score", type=float, required=True,
                        help=f"the detector's own score that the product's threshold ({SCORE_THRESHOLD}) should keep")


def config_from_args(args: argparse.Namespace) -> OperatingPointConfig:
    heatmap_shift(args.score)  # a score outside (0, 1): refused before any file is read
    return OperatingPointConfig(args.source, args.target, args.score)


def main(cfg: OperatingPointConfig) -> dict[str, Any]:
    """Write the copy; its record (``extra["operating_point"]``) and where it went."""
    return {"checkpoint": cfg.target, **write_operating_point(cfg.source, cfg.target, cfg.score)}


def format_result(result: dict[str, Any]) -> str:
    return (f"{result['checkpoint']}: scores of {result['score']} now meet the threshold {result['threshold']} "
            f"(heatmap logits {result['shift']:+.3f})")


if __name__ == "__main__":
    sys.exit(run_module("pipelines.training.operating_point"))
