"""``radarseg upload-check`` and ``models summary``: what a Ray job would upload, the models' size and cost."""

from __future__ import annotations

import argparse
import json
from typing import Any

from pipelines.radar_option import add_radar_option
from radar.profiles import BUILTIN_PRESETS


def add_commands(sub: Any) -> None:
    """upload-check and models summary."""
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


def _cmd_models_summary(args: argparse.Namespace) -> int:

    from pipelines.evaluation.summary import SHIPPED, format_summary, models_summary

    rows = models_summary(tuple(args.profile or ()), tuple(args.checkpoint or SHIPPED))
    print(json.dumps(rows, indent=2) if args.json else format_summary(rows))
    return 0
