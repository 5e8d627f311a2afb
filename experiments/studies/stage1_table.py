"""The stage-1 issue's table from ``radarseg evaluate`` runs: one row per (pair, store), the issue's goals checked.

    .venv/bin/python -m experiments.studies.stage1_table "shipped/25270=runs/lc/eval-shipped-25270" ... \
        [--out experiments/reports/stage1_candidates.json]

Each argument is ``LABEL=RUN`` where ``RUN`` is an ``evaluate --out`` directory (its ``metrics.json``). Rows print
as a Markdown table; the JSON holds the rows and, per row, which goal of issue 34 it meets.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

GOALS = {  # issue 34: per pair and fresh seed
    "ped_iou_ra": (">=", 38.0), "ped_iou_rd": (">=", 38.0), "rg_recall": (">=", 0.935), "roi_voxels_k": ("<=", 26.5),
    "mAP": (">=", 0.65), "ra_miou": (">=", 68.0), "rd_miou": (">=", 68.0), "gmacs": ("<=", 1.8),
}
COLUMNS = ("mAP", "ap1", "ra_miou", "rd_miou", "ped_iou_ra", "ped_iou_rd", "cyc_iou_ra", "cyc_iou_rd", "rg_recall",
           "roi_voxels_k", "gmacs")


def row_of(metrics: dict) -> dict[str, float]:
    seg, rg, det = metrics["segmentation"], metrics["region_growing"]["predicted_seeds"], metrics["detection"]
    return {"mAP": det["mAP"], "ap1": det["AP@1"],
            "ra_miou": 100 * seg["RA"]["mIoU"], "rd_miou": 100 * seg["RD"]["mIoU"],
            "ped_iou_ra": 100 * seg["RA"]["iou"]["pedestrian"], "ped_iou_rd": 100 * seg["RD"]["iou"]["pedestrian"],
            "cyc_iou_ra": 100 * seg["RA"]["iou"]["cyclist"], "cyc_iou_rd": 100 * seg["RD"]["iou"]["cyclist"],
            "rg_recall": rg["recall"], "roi_voxels_k": rg["roi_voxels_mean"] / 1e3,
            "gmacs": metrics["cost"]["macs_mean"]["total"] / 1e9, "frames": metrics["frames"]}


def meets(row: dict[str, float]) -> dict[str, bool]:
    return {k: (row[k] >= v if op == ">=" else row[k] <= v) for k, (op, v) in GOALS.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="LABEL=RUN")
    parser.add_argument("--out", help="JSON of the rows")
    args = parser.parse_args()
    rows = []
    for item in args.runs:
        label, _, run = item.partition("=")
        metrics = json.loads((Path(run) / "metrics.json").read_text())
        row = {"label": label, "run": run, **row_of(metrics)}
        row["goals_met"] = meets(row)
        rows.append(row)
    print("| pair / store | frames | " + " | ".join(COLUMNS) + " | goals met |")
    print("|---|---|" + "---|" * len(COLUMNS) + "---|")
    for row in rows:
        cells = [f"{row[c]:.3f}" if c in ("mAP", "ap1", "rg_recall", "gmacs") else f"{row[c]:.1f}" for c in COLUMNS]
        met = sum(row["goals_met"].values())
        print(f"| {row['label']} | {row['frames']} | " + " | ".join(cells) + f" | {met} / {len(GOALS)} |")
    if args.out:
        Path(args.out).write_text(json.dumps({"goals": GOALS, "rows": rows, "load_average": os.getloadavg()},
                                             indent=1) + "\n")


if __name__ == "__main__":
    main()
