"""``report.md`` from the metrics of :func:`pipelines.evaluation.evaluate.evaluate`: tables in the paper's form
(docs/design.md section 12: mIoU in % per view, MACs in G; detection AP at 1/3/5 m and mAP; region-growing
recall and visited points with a D_thresh sweep), cost per stage and the pictures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

PAPER_REFERENCE = {  # docs/design.md section 12, ERASE-Net (M); for context only (other data, other radars)
    "NXP": {"RD": 73.70, "RA": 57.02, "mAP": 0.853, "macs_g": "12.0 + 1.46"},
    "CARRADA": {"RD": 53.57, "RA": 43.95, "mAP": 0.52, "macs_g": "8.41 + 0.49"},
}


def fmt_pct(value: float | None) -> str:
    return "-" if value is None or value != value else f"{100 * value:.2f}"


def fmt_num(value: float | None, fmt: str = ".3f") -> str:
    return "-" if value is None or value != value else format(value, fmt)


def md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(row) + " |" for row in rows)]


def render_report(metrics: dict[str, Any]) -> str:
    """The markdown text of a report (see the module docstring)."""
    lines = [*_summary(metrics), *_detection(metrics["detection"]), *_segmentation(metrics),
             *_region_growing(metrics["region_growing"]), *_cost(metrics["cost"]), *_training(metrics)]
    lines += ["", "## Pictures", ""]
    lines += [f"![{name}]({name})" for name in metrics["pictures"]]
    return "\n".join(lines) + "\n"


def _summary(metrics: dict[str, Any]) -> list[str]:
    det, rg, seg = metrics["detection"], metrics["region_growing"], metrics["segmentation"]
    macs = metrics["cost"]["macs_mean"]
    lines = [
        f"# ERASE-Net evaluation: {metrics['preset']} / {metrics['split']}",
        "",
        f"Store `{metrics['store']}`, split `{metrics['split']}`, {metrics['frames']} frames. Detector "
        f"`{metrics['detector']}` ({metrics['models']['detector']}), segmenter `{metrics['segmenter']}` "
        f"({metrics['models']['segmenter']}), seed score threshold {metrics['score_threshold']}.",
        "",
        "## Summary (paper's form: mIoU %, background included; MACs in G per frame, segmenter + detector)",
        "",
    ]
    macs_text = f"{macs.get('segment', 0) / 1e9:.3f} + {macs.get('detect', 0) / 1e9:.3f}"
    lines += md_table(["set / view", "ERASE-Net (this model)"],
                    [[f"{metrics['preset']} RD", fmt_pct(seg["RD"]["mIoU"])],
                     [f"{metrics['preset']} RA", fmt_pct(seg["RA"]["mIoU"])],
                     ["detection mAP", fmt_num(det["mAP"])],
                     ["region-growing recall (predicted seeds)", fmt_num(rg["predicted_seeds"]["recall"])],
                     [f"MACs ({metrics['preset']})", macs_text]])
    lines += ["", "Paper, ERASE-Net (M), for context (other radars and data, not comparable figures): "
              + "; ".join(f"{name} RD {ref['RD']} / RA {ref['RA']} mIoU, mAP {ref['mAP']}, MACs {ref['macs_g']} G"
                          for name, ref in PAPER_REFERENCE.items()) + ".", ""]
    return lines


def _detection(det: dict[str, Any]) -> list[str]:
    lines = ["## Detection", "",
              "A prediction matches a ground-truth centre within k metres (Cartesian) and k Doppler bins; "
              f"greedy by score; COCO-interpolated AP; {det['n_truth']} objects, {det['n_predictions']} "
              f"detections down to score {det['ap_score_threshold']}.", ""]
    lines += md_table(["k", "1", "3", "5", "mAP"],
                    [["AP", fmt_num(det["AP@1"]), fmt_num(det["AP@3"]), fmt_num(det["AP@5"]), fmt_num(det["mAP"])]])
    return lines


def _segmentation(metrics: dict[str, Any]) -> list[str]:
    seg, classes = metrics["segmentation"], metrics["classes"]
    lines = ["", "## Segmentation (one confusion matrix per view over the split)", ""]
    header = ["view", *[f"IoU {c}" for c in classes], "mIoU"]
    rows = [[view, *[fmt_pct(seg[view]["iou"][c]) for c in classes], fmt_pct(seg[view]["mIoU"])]
            for view in ("RA", "RD")]
    if "segmentation_truth_seeds" in metrics:
        oracle = metrics["segmentation_truth_seeds"]
        rows += [[f"{view} (true centres as seeds)", *[fmt_pct(oracle[view]["iou"][c]) for c in classes],
                  fmt_pct(oracle[view]["mIoU"])] for view in ("RA", "RD")]
    lines += md_table(header, rows)
    return lines


def _region_growing(rg: dict[str, Any]) -> list[str]:
    config = rg["config"]
    lines = ["", "## Region growing", "",
              f"Recall = ground-truth object voxels inside the ROI / all of them (pooled over frames). "
              f"D_thresh {config['distance_m']} m, I_thresh ratio {config['intensity_ratio']}, floor "
              f"{config['min_snr_db']} dB above the noise, bridge {config['bridge']}.", ""]
    lines += md_table(["seeds", "recall", "visited points / frame", "ROI voxels / frame"],
                    [[name, fmt_num(rg[key]["recall"]), fmt_num(rg[key]["visited_mean"], ".0f"),
                      fmt_num(rg[key]["roi_voxels_mean"], ".0f")]
                     for name, key in (("predicted", "predicted_seeds"), ("true centres", "truth_seeds"))])
    if rg["sweep"]:
        distances = sorted({row["distance_m"] for row in rg["sweep"]})
        by = {(row["seeds"], row["distance_m"]): row for row in rg["sweep"]}
        frames = rg["sweep"][0]["frames"]
        lines += ["", f"D_thresh sweep ({frames} frames):", ""]
        lines += md_table(["D_thresh (m)", "recall (predicted)", "visited (predicted)", "recall (true centres)",
                         "visited (true centres)"],
                        [[f"{d:g}", fmt_num(by[("predicted", d)]["recall"]),
                          fmt_num(by[("predicted", d)]["visited_mean"], ".0f"),
                          fmt_num(by[("truth", d)]["recall"]), fmt_num(by[("truth", d)]["visited_mean"], ".0f")]
                         for d in distances])
    return lines


def _cost(cost: dict[str, Any]) -> list[str]:
    macs, seconds = cost["macs_mean"], cost["seconds_mean"]
    lines = ["", "## Cost per frame (mean)", ""]
    lines += md_table(["stage", "params", "MACs (G)", "seconds"],
                    [["transform", "-", "-", fmt_num(seconds.get("transform"), ".4f")],
                     ["detect", f"{cost['params']['detector']:,}", fmt_num(macs.get("detect", 0) / 1e9, ".4f"),
                      fmt_num(seconds.get("detect"), ".4f")],
                     ["grow", "-", "0", fmt_num(seconds.get("grow"), ".4f")],
                     ["segment", f"{cost['params']['segmenter']:,}", fmt_num(macs.get("segment", 0) / 1e9, ".4f"),
                      fmt_num(seconds.get("segment"), ".4f")],
                     ["project", "-", "-", fmt_num(seconds.get("project"), ".4f")],
                     ["total", f"{cost['params']['total']:,}", fmt_num(macs.get("total", 0) / 1e9, ".4f"),
                      fmt_num(seconds.get("total"), ".4f")]])
    return lines


def _training(metrics: dict[str, Any]) -> list[str]:
    lines: list[str] = []
    training = metrics.get("training", {})
    if training:
        lines += ["", "## Training (from the checkpoints)", ""]
        lines += md_table(["stage", "profile", "epochs", "steps", "training time (s)", "validation"],
                        [[stage, str(info.get("profile")), str(info.get("epoch")), str(info.get("step")),
                          fmt_num(info.get("elapsed_s"), ".0f"),
                          ", ".join(f"{k.removeprefix('val_')} {fmt_num(v)}" for k, v in info.items()
                                    if k.startswith("val_") and isinstance(v, float))]
                         for stage, info in training.items()])
    return lines


def write_report(metrics: dict[str, Any], path: str | Path) -> Path:
    """Write :func:`render_report` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render_report(metrics))
    return path
