"""Learning curves of training runs against training CPU minutes: for segmenter runs validation RA/RD mIoU and
pedestrian IoU, for detector runs (``--stage detector``) validation mAP and each class's recall at the operating
point (seeds at the score threshold matched within 3 m).

Reads each run's ``curve.jsonl`` (``radarseg train segmenter --curve-every STEPS``: a validation before the first
step, every STEPS steps and at each epoch's end, with the training CPU seconds spent to reach it, validation
excluded) and writes the curves into one JSON file and one picture (four panels). Runs are named ``NAME=RUN_DIR``;
``NAME=RUN_DIR@MINUTES`` starts a run's curve at MINUTES (a run that continued another's checkpoint, drawn after it);
``NAME=RUN_DIR#single`` draws a detector that reads history as scored on single cubes (its ``val_*_single`` figures).

    .venv/bin/python -m benchmarks.learning_curves "CE=runs/lc/ft-ce" "CE+Lovasz=runs/lc/ft-ce-lovasz" \\
        --out reports/learning_curves
    .venv/bin/python -m benchmarks.learning_curves --stage detector "quick=runs/lc/det-quick" \\
        --out reports/stage1_curves
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

PANELS = {
    "segmenter": (("val_RA_mIoU", "RA mIoU"), ("val_RD_mIoU", "RD mIoU"),
                  ("val_RA_iou_pedestrian", "pedestrian IoU, RA"), ("val_RD_iou_pedestrian", "pedestrian IoU, RD")),
    "detector": (("val_mAP", "mAP (1/3/5 m)"), ("val_recall_pedestrian", "pedestrian recall at the threshold"),
                 ("val_recall_cyclist", "cyclist recall at the threshold"),
                 ("val_recall_car", "car recall at the threshold")),
}
KEPT = ("epoch", "step", "cpu_s", "elapsed_s", "val_mIoU", "val_roi_recall", "val_AP@1", "val_AP@3", "val_AP@5",
        "val_loss") + tuple(key for panels in PANELS.values() for key, _ in panels) + (
    "val_RA_iou_cyclist", "val_RD_iou_cyclist", "val_RA_iou_car", "val_RD_iou_car")


def read_curve(run_dir: Path, start_minutes: float = 0.0, suffix: str = "") -> dict[str, Any]:
    """One run's points (the figures of :data:`KEPT`), its resolved configuration and its command's options;
    ``start_minutes`` is where its x axis starts (the CPU minutes of the run it continued); ``suffix``: read each
    validation figure ``val_X`` from ``val_X{suffix}`` (``_single``: a history detector on single cubes)."""
    path = run_dir / "curve.jsonl"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no learning curve (train with --curve-every STEPS)")
    points = [json.loads(line) for line in path.read_text().splitlines() if line]
    config = json.loads((run_dir / "config.json").read_text())
    return {"run": str(run_dir), "config": config, "start_cpu_minutes": start_minutes,
            "points": [{key: point.get(key + suffix if key.startswith("val_") else key) for key in KEPT}
                       for point in points]}


def plot(curves: dict[str, dict[str, Any]], path: Path, panels: tuple[tuple[str, str], ...]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, 2, figsize=(10, 7), sharex=True)
    for axis, (key, title) in zip(axes.ravel(), panels, strict=True):
        for name, curve in curves.items():
            points = [p for p in curve["points"] if p.get(key) is not None]
            minutes = [curve["start_cpu_minutes"] + p["cpu_s"] / 60 for p in points]
            axis.plot(minutes, [100 * p[key] for p in points], marker="o", markersize=3, label=name)
        axis.set_title(title)
        axis.set_ylabel("% (validation)")
        axis.grid(alpha=0.3)
    for axis in axes[1]:
        axis.set_xlabel("training CPU minutes (one thread; validation excluded)")
    axes[0, 0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="NAME=RUN_DIR")
    parser.add_argument("--out", default="reports/learning_curves", help="writes OUT.json and OUT.png")
    parser.add_argument("--stage", choices=sorted(PANELS), default="segmenter", help="which figures to draw")
    args = parser.parse_args()
    curves = {}
    for item in args.runs:
        name, sep, run = item.partition("=")
        run, hashed, reading = run.partition("#")
        run, at, start = run.partition("@")
        if not sep or not name or not run or hashed and reading != "single":
            parser.error(f"runs are NAME=RUN_DIR, NAME=RUN_DIR@MINUTES or NAME=RUN_DIR#single, got {item!r}")
        try:
            start_minutes = float(start) if at else 0.0
        except ValueError:
            parser.error(f"the start after @ must be CPU minutes, got {start!r} in {item!r}")
        curves[name] = read_curve(Path(run), start_minutes, "_single" if hashed else "")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {"load_average": os.getloadavg(), "curves": curves}
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    panels = PANELS[args.stage]
    plot(curves, out.with_suffix(".png"), panels)
    for name, curve in curves.items():
        last = curve["points"][-1]
        print(f"{name}: {len(curve['points'])} points, {last['cpu_s'] / 60:.1f} CPU min, "
              + ", ".join(f"{title} {100 * last[key]:.1f}" for key, title in panels if last.get(key) is not None))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
