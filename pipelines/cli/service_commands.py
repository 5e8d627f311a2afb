"""``radarseg serve`` and ``demo``: the HTTP service, and the whole chain end to end on embedded defaults."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from pipelines.runtime_option import add_runtime_option, runtime_of
from radar.errors import UserError


def add_commands(sub: Any) -> None:
    """serve and demo."""
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
