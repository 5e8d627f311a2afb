"""``report.md`` from the metrics of :func:`pipelines.evaluation.evaluate.evaluate`: tables in the paper's form
(docs/design.md section 12: mIoU in % per view, MACs in G; detection AP at 1/3/5 m and mAP; region-growing
recall and visited points with a D_thresh sweep), cost per stage and the pictures."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipelines.evaluation.tracking import match_key

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
             *_region_growing(metrics["region_growing"]), *tracking_lines(metrics.get("tracking")),
             *_cost(metrics["cost"]), *_training(metrics)]
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
        f"({metrics['models']['segmenter']}), centre score threshold {metrics['score_threshold']}.",
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
    headline = tracking_headline(metrics.get("tracking"))
    lines += ["", f"{headline[0].upper()}{headline[1:]}."]
    lines += ["", "Paper, ERASE-Net (M), for context (other radars and data, not comparable figures): "
              + "; ".join(f"{name} RD {ref['RD']} / RA {ref['RA']} mIoU, mAP {ref['mAP']}, MACs {ref['macs_g']} G"
                          for name, ref in PAPER_REFERENCE.items()) + ".", ""]
    return lines


def _detection(det: dict[str, Any]) -> list[str]:
    lines = ["## Detection", "",
              "A prediction matches a ground-truth centre within k metres (Cartesian) and k Doppler bins; "
              f"greedy by score; COCO-interpolated AP; {det['n_truth']} objects, {det['n_predictions']} "
              f"detections down to score {det['ap_score_threshold']}."
              + (f" Thresholds for this radar: {det['thresholds']}." if "thresholds" in det else ""), ""]
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
    later = metrics.get("frames_with_history")
    if later and later["frames"]:
        rows += [[f"{view} (frames after the first {later['from_frame_index']} of a sequence)",
                  *[fmt_pct(later["segmentation"][view]["iou"][c]) for c in classes],
                  fmt_pct(later["segmentation"][view]["mIoU"])] for view in ("RA", "RD")]
    lines += md_table(header, rows)
    if later and later["frames"]:
        lines += ["", f"Region-growing recall on those {later['frames']} frames: "
                      f"{fmt_num(later['region_growing_recall'])}."]
    if priors := metrics.get("track_priors"):
        lines += ["", f"Tracks as priors: {priors['seeds_added']} seeds added where a confirmed track's prediction "
                      f"had no detection (score >= {priors['threshold']:g} within {priors['gate_m']:g} m)."]
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


TRACKING_SOURCES = {"predicted": "predicted objects", "truth_centres": "true centres"}


def tracking_headline(tracking: dict[str, Any] | None) -> str:
    """One line: MOTA and IDF1 at the match distance, every object and confirmed tracks only, both sources."""
    if not tracking:
        return "tracking: not evaluated"
    if "skipped" in tracking:
        return f"tracking: skipped: {tracking['skipped']}"
    key = match_key(tracking["match_distance_m"])
    parts = []
    for source, name in TRACKING_SOURCES.items():
        a, c = (tracking[source][v][key]["overall"] for v in ("all_objects", "confirmed"))
        parts.append(f"{name} MOTA {fmt_num(a['mota'])} / {fmt_num(c['mota'])}, IDF1 {fmt_num(a['idf1'])} / "
                     f"{fmt_num(c['idf1'])}, {a['num_switches']} / {c['num_switches']} ID switches")
    return (f"tracking ({tracking['match_distance_m']:g} m; all objects / confirmed): " + "; ".join(parts)
            + f"; tracker {fmt_num(tracking['predicted']['tracker_ms_per_frame'].get('median'), '.3f')} ms/frame")


def tracking_lines(tracking: dict[str, Any] | None) -> list[str]:
    """The report's tracking section: CLEAR MOT and identity metrics, per class, velocity errors, cost."""
    if not tracking:
        return []
    lines = ["", "## Tracking", ""]
    if "skipped" in tracking:
        return lines + [f"Not evaluated: {tracking['skipped']}."]
    lines += [f"{tracking['sequences']} sequences, {tracking['frames']} frames, {tracking['truth_tracks']} true "
              f"tracks. A track matches a true object within {tracking['match_distance_m']:g} m "
              f"({tracking['distance']}; {tracking['secondary_distance_m']:g} m in the last columns). Hypotheses: "
              + "; ".join(f"*{k}*: {v}" for k, v in tracking["variants"].items()) + ".", ""]
    first, second = (match_key(tracking[k]) for k in ("match_distance_m", "secondary_distance_m"))
    rows = []
    for source, name in TRACKING_SOURCES.items():
        for variant in tracking["variants"]:
            o, p = tracking[source][variant][first]["overall"], tracking[source][variant][second]["overall"]
            rows.append([name, variant, fmt_num(o["mota"]), fmt_num(o["motp"]), fmt_num(o["idf1"]),
                         str(o["num_switches"]), fmt_num(o["switches_per_100_tracks"], ".1f"),
                         f"{o['mostly_tracked']} / {o['mostly_lost']} of {o['num_unique_objects']}",
                         str(o["num_false_positives"]), str(o["num_misses"]), fmt_num(p["mota"]), fmt_num(p["idf1"])])
    lines += md_table(["source", "hypotheses", "MOTA", "MOTP (m)", "IDF1", "ID switches", "per 100 tracks",
                       "mostly tracked / lost", "FP", "FN", f"MOTA {second[6:]}", f"IDF1 {second[6:]}"], rows)
    return (lines + _tracking_per_class(tracking, first) + _tracking_velocity(tracking)
            + tracker_comparison_lines(tracking.get("trackers")))


def tracker_comparison_lines(comparison: dict[str, Any] | None) -> list[str]:
    """The trackers compared on the same objects (``tracking.trackers``): GOSPA, HOTA, MOTA, IDF1, velocity, cost."""
    if not comparison:
        return []
    g = comparison["gospa"]
    rows = []
    for name in comparison["names"]:
        r = comparison[name]
        gospa, hota, mot, velocity = r["gospa"], r["hota"], r["mot"], r["velocity"]
        rows.append([name, fmt_num(gospa.get("mean_m")), fmt_num(gospa.get("missed_per_frame"), ".2f"),
                     fmt_num(gospa.get("false_per_frame"), ".2f"), fmt_num(hota["hota"]), fmt_num(hota["deta"]),
                     fmt_num(hota["assa"]), fmt_num(mot["mota"]), fmt_num(mot["idf1"]), str(mot["num_switches"]),
                     fmt_num(velocity["vx_rmse_mps"], ".2f"), fmt_num(velocity["vy_rmse_mps"], ".2f"),
                     fmt_num(r["tracker_ms_per_frame"].get("median"), ".3f")])
    return ["", "### Trackers on the same objects", "",
            f"Each tracker's reported tracks ({comparison['reported']}) against the truth. GOSPA: alpha 2, "
            f"p = {g['p']:g}, c = {g['c_m']:g} m, mean per frame; HOTA with similarity "
            f"{comparison['hota_similarity']}.",
            "",
            *md_table(["tracker", "GOSPA (m)", "missed / frame", "false / frame", "HOTA", "DetA", "AssA", "MOTA",
                       "IDF1", "ID switches", "vx RMSE (m/s)", "vy RMSE (m/s)", "ms / frame"], rows)]


def _tracking_per_class(tracking: dict[str, Any], key: str) -> list[str]:
    rows = []
    for source, name in TRACKING_SOURCES.items():
        for variant in tracking["variants"]:
            for cls, o in tracking[source][variant][key]["per_class"].items():
                rows.append([name, variant, cls, fmt_num(o["mota"]), fmt_num(o["motp"]), fmt_num(o["idf1"]),
                             str(o["num_switches"]), f"{o['mostly_tracked']} / {o['mostly_lost']} of "
                             f"{o['num_unique_objects']}"])
    return ["", f"Per class ({key[6:]}; the truth of a class against the tracks voted that class):", "",
            *md_table(["source", "hypotheses", "class", "MOTA", "MOTP (m)", "IDF1", "ID switches",
                       "mostly tracked / lost"], rows)]


def _tracking_velocity(tracking: dict[str, Any]) -> list[str]:
    rows = []
    for source, name in TRACKING_SOURCES.items():
        velocity = tracking[source]["velocity"]
        for cls, v in [("all", velocity["overall"]), *velocity["per_class"].items()]:
            rows.append([name, cls, fmt_num(v["vx_rmse_mps"]), fmt_num(v["vy_rmse_mps"]),
                         fmt_num(v["heading_rmse_deg"], ".1f"), str(v["n"]), str(v["n_heading"])])
    ms = {source: tracking[source]["tracker_ms_per_frame"] for source in TRACKING_SOURCES}
    return ["", f"Velocity error of matched tracks from their frame {tracking['velocity_min_age']} on (RMSE; "
            f"heading for objects faster than {tracking['heading_min_speed_mps']:g} m/s):", "",
            *md_table(["source", "class", "vx (m/s)", "vy (m/s)", "heading (deg)", "objects", "objects (heading)"],
                      rows),
            "", "Tracker time per frame (ms): " + "; ".join(
                f"{TRACKING_SOURCES[s]} median {fmt_num(m.get('median'), '.3f')}, p99 {fmt_num(m.get('p99'), '.3f')}"
                for s, m in ms.items()) + "."]


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
        lines += md_table(["stage", "recipe", "epochs", "steps", "training time (s)", "validation"],
                        [[stage, str(info.get("recipe")), str(info.get("epoch")), str(info.get("step")),
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
