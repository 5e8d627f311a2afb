"""Stage-1 diagnosis (issue 34, point 1): where the true objects are lost between the detector and region growing.

For every true object of every scored frame (the store's object table; its voxels are ``instances == instance_id``)
it runs the shipped pair (``EraseNet.from_checkpoints``, the operating threshold is the model's default 0.3) and
decides whether the object is *found*: a seed of the operating point is matched to it (the greedy rule of
:func:`radar.metrics.match_frame`, within ``--match-k`` metres and Doppler bins, default 3 as AP@3) and at least
``--min-share`` (0.5) of its voxels lie in the region grown from that seed. Otherwise the first cause that
applies, in this order:

- ``a_no_peak``: the detector heatmap stays below ``--floor`` (0.05) on every stride-4 cell within the match radius
  (the cell holding the true centre always counts);
- matched seed, but its region does not hold the object's voxels: ``d_region`` when most of them belong to the
  region of a seed matched to another true object (grown first: seeds grow in score order and the first keeps a
  voxel), ``e_false_seed`` when they belong to a seed matched to none, else ``c_growth`` (the seed is placed,
  moved or bounded so that growth does not reach them);
- unmatched with an operating seed within the match radius: ``d_peak`` when such a seed (Doppler within k too)
  was taken by another true object (two objects under one peak), else ``c_doppler`` (the seed is in the wrong
  Doppler bin);
- unmatched, no operating seed within the match radius: ``c_misplaced`` when an unmatched operating seed whose
  nearest true object is this one lies within the region-growing distance D_thresh; ``b_below_threshold`` when a
  decoded heatmap peak (3x3 local maximum) within the radius scores in [floor, threshold); with no local maximum
  above the floor within the radius, ``d_suppressed`` when the nearest such peak is an operating seed matched to
  another object within D_thresh (the object sits on that seed's slope), else ``a_no_own_peak`` (the heat near it
  is background or a slope, no peak of its own: letter (a) like ``a_no_peak``).

Also per class: counts, the detected (matched) fraction at k = 1, 3, 5, pooled region-growing voxel recall from the
operating seeds and from the true centres (as ``radarseg evaluate``: ``grow_regions`` with the model's
configuration), the heatmap peak score of each object (max of the heatmap within the match radius; quantiles and a
histogram), AP@1/3/5 and mAP from :class:`DetectionScorer` (peaks down to ``AP_SCORE_THRESHOLD``, as
``evaluate``) and threshold what-ifs: a global score threshold sweep, an oracle "pedestrian-only" lower threshold
(extra peaks in [t, 0.3) kept only when their nearest true object within the match rule is a pedestrian: the best a
per-class threshold could do, at its least ROI cost) and a segmenter-gated one (detect at t, segment everything,
keep a low-score seed only when its region is segmented mostly as pedestrian: what a class-agnostic heatmap
permits; the segmenter pays the whole ROI at t). Pictures of pedestrian misses (RA view) and of the peak scores go
to ``--pictures-dir``. The what-if table also gives, per class and operating cause, what the same objects
become at the lower threshold, and where its extra seeds fall (matched, near an object of a class, clutter).

    .venv/bin/python -m experiments.studies.stage1_diagnosis --store out/stage1/seed25270.zarr \\
        --store out/stage1/seed25280.zarr --threads 1 --out experiments/reports/stage1.json

Stores: ``radarseg preprocess --source sim --preset small --sequences 48 --frames 4 --seed S --out ...`` (every frame
of every split is scored; ``--frames N`` scores N evenly spread frames per store).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from models.checkpoint import load_checkpoint
from models.erasenet.detection import detect_centres
from models.erasenet.model import EraseNet
from models.heap import freeze_loaded_heap
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.spread import spread
from pipelines.datasets.store import CENTRE_COLUMNS, OBJECT_COLUMN, frames_of_split, open_store
from pipelines.evaluation.evaluate import AP_SCORE_THRESHOLD
from pipelines.evaluation.scoring import DetectionScorer
from radar.centres import Centres
from radar.input_kind import InputKind
from radar.metrics import match_frame
from radar.region_growing import grow_regions

REPO = Path(__file__).resolve().parents[2]
CAUSES = ("a_no_peak", "a_no_own_peak", "b_below_threshold", "c_doppler", "c_misplaced", "c_growth", "d_peak",
          "d_suppressed", "d_region", "e_false_seed")
CAUSE_LETTER = {"a_no_peak": "a", "a_no_own_peak": "a", "b_below_threshold": "b", "c_doppler": "c",
                "c_misplaced": "c", "c_growth": "c", "d_peak": "d", "d_suppressed": "d", "d_region": "d",
                "e_false_seed": "e"}
QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)
HIST_EDGES = np.round(np.linspace(0.0, 1.0, 21), 3)
SWEEP = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3)


# --------------------------------------------------------------------------- matching
def assign(pred_xy, pred_doppler, pred_score, truth_xy, truth_doppler, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching of :func:`radar.metrics.match_frame` with its assignment: ``seed_truth`` (N,) index of the
    matched true object or -1, ``truth_seed`` (M,) the matched seed or -1. Checked against match_frame's output."""
    pred_xy = np.asarray(pred_xy, np.float64).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, np.float64).reshape(-1, 2)
    seed_truth = np.full(len(pred_xy), -1, np.int64)
    truth_seed = np.full(len(truth_xy), -1, np.int64)
    if len(pred_xy) and len(truth_xy):
        distance = np.linalg.norm(pred_xy[:, None, :] - truth_xy[None, :, :], axis=2)
        eligible = (distance <= k) & (np.abs(np.asarray(pred_doppler)[:, None] - np.asarray(truth_doppler)[None]) < k)
        for i in np.argsort(-np.asarray(pred_score, np.float64), kind="stable"):
            candidates = np.flatnonzero(eligible[i] & (truth_seed < 0))
            if len(candidates):
                j = candidates[np.argmin(distance[i, candidates])]
                truth_seed[j], seed_truth[i] = i, j
    tp = match_frame(pred_xy, pred_doppler, pred_score, truth_xy, truth_doppler, k)
    if not np.array_equal(tp, seed_truth >= 0):
        raise AssertionError("assignment disagrees with radar.metrics.match_frame")
    return seed_truth, truth_seed


def take(centres, keep):
    """The centres where ``keep`` (bool or index array), in their order."""
    keep = np.asarray(keep)
    return Centres(centres.score[keep], centres.range_bin[keep], centres.angle_bin[keep],
                        centres.doppler_bin[keep])


# --------------------------------------------------------------------------- one frame
def history_tensors(history: list[np.ndarray | None] | None, shape: tuple[int, ...]) -> dict[str, torch.Tensor]:
    """``detect_centres``' ``history`` (1, H, D, R, A) dB, zero where absent, and ``history_present`` (1, H); no
    keyword at all for a one-frame detector."""
    if history is None:
        return {}
    earlier = [np.zeros(shape, np.float32) if frame is None else frame for frame in history]
    cubes = torch.from_numpy(np.stack([frame.transpose(2, 0, 1) for frame in earlier]))[None]
    return {"history": cubes, "history_present": torch.tensor([[frame is not None for frame in history]])}


class Frame:
    """One frame's truth and detector output; :meth:`status` scores any seed set against it."""

    def __init__(self, net, log_power: np.ndarray, instances: np.ndarray, table: np.ndarray, args, cells_xy,
                 history: list[np.ndarray | None] | None = None):
        col, profile = OBJECT_COLUMN, net.profile
        self.net, self.args, self.profile = net, args, profile
        self.history = history  # the earlier frames a detector that reads them gets (None: one frame)
        self.log_power, self.instances, self.table = log_power, instances, table
        self.class_id = table[:, col["class_id"]].astype(int)
        self.truth_xy = table[:, [col["x"], col["y"]]]
        self.truth_doppler = table[:, col["doppler_bin"]]
        ids = table[:, col["instance_id"]].astype(int)
        flat = instances.reshape(-1)
        self.voxels = [np.flatnonzero(flat == i) for i in ids]  # flat indices of each object's voxels
        self.n_voxels = np.array([len(v) for v in self.voxels])
        dra = torch.from_numpy(np.ascontiguousarray(log_power.transpose(2, 0, 1)))[None]  # (1, D, R, A)
        with torch.no_grad():  # every 3x3 peak down to AP_SCORE_THRESHOLD, Doppler refined as EraseNet does
            outputs, (peaks,) = detect_centres(net.detector, dra, mean_db=net.mean_db, std_db=net.std_db,
                                                    k=args.peaks, score_threshold=AP_SCORE_THRESHOLD,
                                                    doppler_refinement=net.doppler_refinement,
                                                    **history_tensors(history, log_power.shape))
        self.heatmap = outputs["heatmap"][0, 0].float().numpy()
        self.peaks = peaks  # sorted by descending score
        self.peaks_xy = np.stack(profile.xy(peaks.range_bin, peaks.angle_bin), axis=1).reshape(-1, 2)
        # heat near each object: the heatmap's max over cells within k metres (the centre's own cell always)
        cell_x, cell_y = cells_xy
        k = args.match_k
        self.heat = np.zeros(len(table))
        self.best_peak = np.zeros(len(table))
        stride = 4
        for j, (x, y) in enumerate(self.truth_xy):
            near = (cell_x - x) ** 2 + (cell_y - y) ** 2 <= k * k
            r, a = table[j, col["range_bin"]], table[j, col["angle_bin"]]
            near[min(int(r // stride), near.shape[0] - 1), min(int(a // stride), near.shape[1] - 1)] = True
            self.heat[j] = float(self.heatmap[near].max())
            within = np.linalg.norm(self.peaks_xy - (x, y), axis=1) <= k
            self.best_peak[j] = float(peaks.score[within].max()) if within.any() else 0.0

    def seeds_at(self, threshold: float):
        """The top ``max_objects`` peaks scoring >= ``threshold`` (EraseNet's decode at that threshold)."""
        keep = np.flatnonzero(self.peaks.score >= threshold)[: self.net.max_objects]
        return take(self.peaks, keep)

    def status(self, centres, regions) -> dict:
        """Per object: matched at k = 1, 3, 5 and the chosen k, own / ROI voxel share, found, cause."""
        profile, args = self.profile, self.args
        k, floor, _thr = args.match_k, args.floor, self.net.score_threshold
        n = len(self.table)
        seed_xy = np.stack(profile.xy(centres.range_bin, centres.angle_bin), axis=1).reshape(-1, 2)
        matched = {}
        for kk in sorted({1.0, 3.0, 5.0, k}):
            matched[kk] = assign(seed_xy, centres.doppler_bin, centres.score, self.truth_xy, self.truth_doppler, kk)
        seed_truth, truth_seed = matched[k]
        owner = np.full(self.instances.size, -1, np.int64)  # seed owning each ROI voxel
        if len(regions):
            owner[np.ravel_multi_index(tuple(regions.voxels.T), self.instances.shape)] = regions.seed_index
        own_share, roi_share, causes, detail = np.zeros(n), np.zeros(n), [], []
        seed_nearest = (np.argmin(np.linalg.norm(seed_xy[:, None] - self.truth_xy[None], axis=2), axis=1)
                        if len(seed_xy) and n else np.zeros(len(seed_xy), int))
        for j in range(n):
            owners = owner[self.voxels[j]]
            counts = np.bincount(owners[owners >= 0], minlength=len(centres))
            size = max(self.n_voxels[j], 1)
            roi_share[j] = counts.sum() / size
            s = truth_seed[j]
            own_share[j] = counts[s] / size if s >= 0 else 0.0
            dist = np.linalg.norm(seed_xy - self.truth_xy[j], axis=1) if len(seed_xy) else np.zeros(0)
            info = {}
            if s >= 0 and own_share[j] >= args.min_share:
                cause = "found"
            elif self.heat[j] < floor:
                cause = "a_no_peak"
            elif s >= 0:
                others = counts.copy()
                others[s] = 0
                if (others.sum() / size >= args.min_share
                        or (others.sum() > counts[s] and roi_share[j] >= args.min_share)):
                    top = int(np.argmax(others))
                    cause = "d_region" if seed_truth[top] >= 0 else "e_false_seed"
                    info["owner_score"] = float(centres.score[top])
                else:
                    cause = "c_growth"
                info["seed_distance_m"] = float(dist[s])
            else:
                near = np.flatnonzero(dist <= k)
                if len(near):
                    doppler_ok = near[np.abs(centres.doppler_bin[near] - self.truth_doppler[j]) < k]
                    if len(doppler_ok):  # eligible seeds, all matched to other objects
                        cause = "d_peak"
                    else:
                        cause = "c_doppler"
                        info["doppler_error"] = float(np.min(np.abs(centres.doppler_bin[near] - self.truth_doppler[j])))
                else:
                    mis = np.flatnonzero((seed_truth < 0) & (seed_nearest == j)
                                         & (dist <= self.net.region_config.distance_m))
                    if len(mis):
                        cause = "c_misplaced"
                        info["seed_distance_m"] = float(dist[mis].min())
                    elif self.best_peak[j] >= floor:
                        cause = "b_below_threshold"
                    else:  # no local maximum >= floor within the radius: the heat there is a slope or background
                        cause = "a_no_own_peak"
                        strong = np.flatnonzero(self.peaks.score >= floor)
                        if len(strong) and len(seed_xy):
                            gap = np.linalg.norm(self.peaks_xy[strong] - self.truth_xy[j], axis=1)
                            q = strong[int(np.argmin(gap))]
                            same = np.flatnonzero(np.linalg.norm(seed_xy - self.peaks_xy[q], axis=1) < 1e-6)
                            info["nearest_peak_m"] = float(gap.min())
                            info["nearest_peak_score"] = float(self.peaks.score[q])
                            if (len(same) and seed_truth[same[0]] >= 0
                                    and gap.min() <= self.net.region_config.distance_m):
                                cause = "d_suppressed"  # on the slope of another object's seed
            causes.append(cause)
            detail.append(info)
        return {"matched": {kk: v[1] >= 0 for kk, v in matched.items()}, "own_share": own_share,
                "roi_share": roi_share, "cause": causes, "detail": detail, "seed_truth": seed_truth}

    def grow(self, centres):
        return grow_regions(self.log_power, centres, self.profile, self.net.region_config)

    def truth_recall_voxels(self) -> np.ndarray:
        """Voxels of each object inside the ROI grown from the true centres (as ``evaluate`` does)."""
        centres = Centres.from_bins(self.table[:, CENTRE_COLUMNS])
        regions = self.grow(centres)
        inside = np.zeros(self.instances.size, bool)
        if len(regions):
            inside[np.ravel_multi_index(tuple(regions.voxels.T), self.instances.shape)] = True
        return np.array([int(inside[v].sum()) for v in self.voxels])


# --------------------------------------------------------------------------- tallies
class Tally:
    """Objects of one store: a row per object plus per-frame ROI figures per seed set."""

    def __init__(self) -> None:
        self.rows: list[dict] = []
        self.roi: dict[str, list[float]] = {}

    def add_roi(self, name: str, value: float) -> None:
        self.roi.setdefault(name, []).append(float(value))


STRATA = {"doppler_from_zero_bins": ("speed", (0.0, 1.0, 2.0, 4.0, np.inf)),
          "range_m": ("range_m", (0.0, 15.0, 30.0, np.inf)),
          "n_voxels": ("n_voxels", (0, 100, 300, 1000, np.inf))}


def strata(objs: list[dict], zero_bin: float) -> dict:
    """Median peak score, found and detected (k = 3) fractions of objects by |Doppler - zero-velocity bin|, range
    and voxel count."""
    out = {}
    for name, (key, edges) in STRATA.items():
        values = np.array([abs(r["doppler_bin"] - zero_bin) if key == "speed" else r[key] for r in objs], float)
        cells = []
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            sel = [r for r, v in zip(objs, values, strict=True) if lo <= v < hi]
            cells.append({"from": lo, "to": None if np.isinf(hi) else hi, "count": len(sel),
                          "peak_median": float(np.median([r["heat"] for r in sel])) if sel else None,
                          "found_fraction": float(np.mean([r["cause"] == "found" for r in sel])) if sel else None,
                          "detected_fraction_k3": float(np.mean([r["matched"]["k3"] for r in sel])) if sel else None})
        out[name] = cells
    return out


def class_table(rows: list[dict], class_names: list[str], low: float, zero_bin: float) -> dict:
    out = {}
    for cid, name in enumerate(class_names):
        if cid == 0:
            continue
        objs = [r for r in rows if r["class_id"] == cid]
        n = len(objs)
        causes = {c: sum(r["cause"] == c for r in objs) for c in ("found", *CAUSES)}
        letters = {letter: sum(v for c, v in causes.items() if CAUSE_LETTER.get(c) == letter) for letter in "abcde"}
        voxels = sum(r["n_voxels"] for r in objs)
        heat = np.array([r["heat"] for r in objs])
        lost = [r for r in objs if r["cause"] != "found"]
        b_peak = np.array([r["best_peak"] for r in objs if r["cause"] == "b_below_threshold"])
        out[name] = {
            "count": n, "voxels": int(voxels),
            "lost_roi_covered_by_cause": {c: sum(r["cause"] == c and r["roi_share"] >= 0.5 for r in objs)
                                          for c in CAUSES},
            "causes": causes, "cause_fractions": {c: (v / n if n else None) for c, v in causes.items()},
            "letters": letters, "letter_fractions_of_lost": {x: (v / len(lost) if lost else None)
                                                           for x, v in letters.items()},
            "found_fraction": causes["found"] / n if n else None,
            "detected_fraction": {f"k{kk:g}": (sum(r["matched"][f"k{kk:g}"] for r in objs) / n if n else None)
                                  for kk in (1.0, 3.0, 5.0)},
            "lost_with_voxels_in_roi": sum(r["roi_share"] >= 0.5 for r in lost),
            "rg_recall_predicted_seeds": sum(r["roi_voxels"] for r in objs) / voxels if voxels else None,
            "rg_recall_true_centres": sum(r["truth_voxels"] for r in objs) / voxels if voxels else None,
            "peak_score_quantiles": ({f"q{int(q * 100)}": float(np.quantile(heat, q)) for q in QUANTILES}
                                     if n else {}),
            "peak_score_mean": float(heat.mean()) if n else None,
            "peak_score_below_floor": float(np.mean(heat < 0.05)) if n else None,
            "peak_score_below_threshold": float(np.mean(heat < 0.3)) if n else None,
            "peak_score_histogram": np.histogram(heat, HIST_EDGES)[0].tolist(),
            "n_voxels_median": float(np.median([r["n_voxels"] for r in objs])) if n else None,
            "b_best_peak_quantiles": ({f"q{int(q * 100)}": float(np.quantile(b_peak, q)) for q in QUANTILES}
                                      if len(b_peak) else {}),
            "b_best_peak_at_least_low": int(np.sum(b_peak >= low)),
            "strata": strata(objs, zero_bin),
            "range_m_median": float(np.median([r["range_m"] for r in objs])) if n else None,
        }
    return out


# --------------------------------------------------------------------------- pictures
def draw_miss(frame: Frame, j: int, seeds, regions, class_names, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    col = OBJECT_COLUMN
    ra = frame.log_power.max(axis=2)
    fig, ax = plt.subplots(figsize=(7.2, 6.0))
    ax.imshow(ra, origin="lower", aspect="auto", cmap="gray", interpolation="nearest")
    stride = 4
    h, w = frame.heatmap.shape
    cy, cx = (np.arange(h) + 0.5) * stride - 0.5, (np.arange(w) + 0.5) * stride - 0.5
    levels = [0.05, 0.15, 0.3, 0.6]
    cs = ax.contour(cx, cy, frame.heatmap, levels=levels, colors=["#4aa3ff", "#8f8fff", "#ffb000", "#ff3030"],
                    linewidths=1.0)
    ax.clabel(cs, fontsize=6, fmt="%.2f")
    if len(regions):
        roi = np.zeros(ra.shape, bool)
        roi[regions.voxels[:, 0], regions.voxels[:, 1]] = True
        ax.contour(np.arange(ra.shape[1]), np.arange(ra.shape[0]), roi.astype(float), levels=[0.5],
                   colors="#00e0a0", linewidths=0.8, linestyles="dashed")
    colours = {1: "#ff4fd8", 2: "#ffe14f", 3: "#4fffff"}
    for i, row in enumerate(frame.table):
        r, a, c = row[col["range_bin"]], row[col["angle_bin"]], int(row[col["class_id"]])
        ax.plot(a, r, "o", mfc="none", mec=colours.get(c, "w"), ms=14 if i == j else 8, mew=2 if i == j else 1)
        ax.annotate(f"{class_names[c]} d={row[col['doppler_bin']]:.1f}", (a, r), xytext=(6, 6),
                    textcoords="offset points", color=colours.get(c, "w"), fontsize=7)
    low = frame.peaks.score >= 0.05
    ax.plot(frame.peaks.angle_bin[low], frame.peaks.range_bin[low], "+", color="#ffb000", ms=7)
    for s in range(len(seeds)):
        ax.plot(seeds.angle_bin[s], seeds.range_bin[s], "x", color="#ff3030", ms=9, mew=2)
        ax.annotate(f"{seeds.score[s]:.2f} d={seeds.doppler_bin[s]:.1f}", (seeds.angle_bin[s], seeds.range_bin[s]),
                    xytext=(6, -10), textcoords="offset points", color="#ff3030", fontsize=7)
    for p in np.flatnonzero(low & (frame.peaks.score < frame.net.score_threshold)):
        ax.annotate(f"{frame.peaks.score[p]:.2f}", (frame.peaks.angle_bin[p], frame.peaks.range_bin[p]),
                    xytext=(4, 4), textcoords="offset points", color="#ffb000", fontsize=6)
    r0, a0 = frame.table[j, col["range_bin"]], frame.table[j, col["angle_bin"]]
    ax.set_xlim(max(a0 - 40, 0), min(a0 + 40, ra.shape[1] - 1))
    ax.set_ylim(max(r0 - 28, 0), min(r0 + 28, ra.shape[0] - 1))
    ax.set_xlabel("angle bin")
    ax.set_ylabel("range bin")
    ax.set_title(title, fontsize=8)
    fig.text(0.01, 0.005, "RA max over Doppler (dB, grey); heatmap contours 0.05/0.15/0.3/0.6; x operating seeds "
             "(>= 0.3, score and Doppler bin); + peaks >= 0.05;\no true centres (big: the miss; pink pedestrian, "
             "yellow cyclist, cyan car; d = Doppler bin); dashed green: ROI (RA projection)", fontsize=6)
    fig.tight_layout(rect=(0, 0.045, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_histograms(results: dict, class_names: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stores = list(results)
    fig, axes = plt.subplots(1, len(stores), figsize=(5.5 * len(stores), 3.8), squeeze=False)
    centres = (HIST_EDGES[:-1] + HIST_EDGES[1:]) / 2
    width = (HIST_EDGES[1] - HIST_EDGES[0]) / 4
    for ax, store in zip(axes[0], stores, strict=True):
        for i, name in enumerate(class_names[1:]):
            row = results[store]["classes"][name]
            hist = np.array(row["peak_score_histogram"], float)
            median = row["peak_score_quantiles"].get("q50", float("nan"))
            ax.bar(centres + (i - 1) * width, hist / max(hist.sum(), 1), width=width,
                   label=f"{name} (n={row['count']}, median {median:.2f})")
        ax.axvline(0.3, color="k", ls="--", lw=0.8)
        ax.axvline(0.05, color="grey", ls=":", lw=0.8)
        ax.set_title(f"{Path(store).name}: heatmap peak within 3 m of each true object", fontsize=8)
        ax.set_xlabel("peak score")
        ax.set_ylabel("fraction of the class's objects")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- main loop
class StoreTally(Tally):
    """Everything :func:`run_store` gathers over one store's frames."""

    def __init__(self) -> None:
        super().__init__()
        self.whatif: dict[str, list[dict]] = {name: [] for name in ("global", "oracle_ped", "gated_ped")}
        self.sweep: dict[float, list] = {t: [] for t in SWEEP}
        self.sweep_roi: dict[float, list] = {t: [] for t in SWEEP}
        self.checked = {"frames": 0, "centres_equal": 0, "regions_equal": 0}
        self.extra_kinds: dict[str, int] = {}
        self.background: list[tuple[float, float, float]] = []


def tally_operating(tally: StoreTally, net, frame: Frame, log_power, slot: int, store: str, ped: int,
                    picture_pool: list):
    """The operating point, through the product's own path: checks it against the diagnosis' decode and growth,
    adds a row per object. Returns its regions and status."""
    result = net.segment(log_power, kind=InputKind.log_power, history=frame.history)
    seeds, regions = result.centres, result.regions
    mine = frame.seeds_at(net.score_threshold)
    checked = tally.checked
    checked["frames"] += 1
    checked["centres_equal"] += int(len(mine) == len(seeds) and np.allclose(mine.bins, seeds.bins, atol=1e-3))
    again = frame.grow(seeds)
    checked["regions_equal"] += int(np.array_equal(again.voxels, regions.voxels))
    status = frame.status(seeds, regions)
    truth_voxels = frame.truth_recall_voxels()
    tally.add_roi("operating", len(regions))
    tally.add_roi("operating_seeds", len(seeds))
    tally.add_roi("operating_false_seeds", int(np.sum(status["seed_truth"] < 0)))
    for j in range(len(frame.table)):
        rng = float(np.hypot(*frame.truth_xy[j]))
        tally.rows.append({
            "slot": slot, "object": j, "class_id": int(frame.class_id[j]), "n_voxels": int(frame.n_voxels[j]),
            "range_m": rng, "heat": frame.heat[j], "best_peak": frame.best_peak[j],
            "doppler_bin": float(frame.truth_doppler[j]),
            "matched": {f"k{kk:g}": bool(v[j]) for kk, v in status["matched"].items()},
            "own_share": float(status["own_share"][j]), "roi_share": float(status["roi_share"][j]),
            "roi_voxels": int(round(status["roi_share"][j] * frame.n_voxels[j])),
            "truth_voxels": int(truth_voxels[j]), "cause": status["cause"][j], **status["detail"][j],
        })
        if frame.class_id[j] == ped and status["cause"][j] != "found":
            picture_pool.append((store, slot, j, status["cause"][j]))
    return regions, status


def tally_sweep(tally: StoreTally, frame: Frame, regions, status, thr: float) -> None:
    """The global threshold sweep, each threshold scored with the same rule."""
    for t in SWEEP:
        s_t = frame.seeds_at(t)
        r_t = regions if t == thr else frame.grow(s_t)
        st = status if t == thr else frame.status(s_t, r_t)
        tally.sweep[t].append(([c == "found" for c in st["cause"]], st["roi_share"]))
        tally.sweep_roi[t].append((len(r_t), len(s_t), int(np.sum(st["seed_truth"] < 0))))


def extra_seed_kind(frame: Frame, s: int, wide_truth, wide_xy, class_names: list[str], dmax: float) -> str:
    """Where an extra seed of the lower threshold falls: matched, near an object of a class, or clutter."""
    if wide_truth[s] >= 0:
        return f"matched_{class_names[frame.class_id[wide_truth[s]]]}"
    if len(frame.table):
        gap = np.linalg.norm(frame.truth_xy - wide_xy[s], axis=1)
        return f"near_{class_names[frame.class_id[int(np.argmin(gap))]]}" if gap.min() <= dmax else "clutter"
    return "clutter"


def tally_lower_threshold(tally: StoreTally, net, frame: Frame, log_power, args, class_names: list[str],
                          ped: int) -> None:
    """The what-ifs at ``--low-threshold``: global, oracle pedestrian-only and segmenter-gated."""
    thr = net.score_threshold
    wide = frame.seeds_at(args.low_threshold)
    # segment every seed >= low
    wide_result = net.segment(log_power, kind=InputKind.log_power, centres=wide, history=frame.history)
    extra = np.flatnonzero(wide.score < thr)
    # oracle: an extra seed stays when the true object it matches (the match rule, k) is a pedestrian
    wide_xy = np.stack(net.profile.xy(wide.range_bin, wide.angle_bin), axis=1).reshape(-1, 2)
    wide_truth, _ = assign(wide_xy, wide.doppler_bin, wide.score, frame.truth_xy, frame.truth_doppler, args.match_k)
    truth_class = np.array([frame.class_id[j] if j >= 0 else -1 for j in wide_truth], int)
    keep_oracle = (wide.score >= thr) | (truth_class == ped)
    # gated: an extra seed stays when its region is segmented mostly as pedestrian
    voxel_class = wide_result.labels[tuple(wide_result.regions.voxels.T)]
    keep_gated = wide.score >= thr
    for s in extra:
        own = voxel_class[wide_result.regions.seed_index == s]
        own = own[own > 0]
        if len(own) and np.bincount(own, minlength=len(class_names)).argmax() == ped:
            keep_gated[s] = True
    dmax = net.region_config.distance_m
    for s in extra:  # where the extra seeds of the lower threshold fall
        kind = extra_seed_kind(frame, s, wide_truth, wide_xy, class_names, dmax)
        tally.extra_kinds[kind] = tally.extra_kinds.get(kind, 0) + 1
    tally.background.append((float(np.median(frame.heatmap)), float(np.quantile(frame.heatmap, 0.9)),
                             float(np.mean(frame.heatmap >= args.floor))))
    for name, keep, compute_roi in (("global", np.ones(len(wide), bool), len(wide_result.regions)),
                                    ("oracle_ped", keep_oracle, None),
                                    ("gated_ped", keep_gated, len(wide_result.regions))):
        s_k = take(wide, keep)
        r_k = wide_result.regions if name == "global" else frame.grow(s_k)
        st = frame.status(s_k, r_k)
        tally.whatif[name].append({"found": ([c == "found" for c in st["cause"]], st["roi_share"]), "roi": len(r_k),
                                   "causes": st["cause"],
                                   "compute_roi": len(r_k) if compute_roi is None else compute_roi,
                                   "seeds": len(s_k), "false_seeds": int(np.sum(st["seed_truth"] < 0))})


def whatif_summary(tally: StoreTally, class_names: list[str], found_lists, roi, seeds, false_seeds,
                   compute_roi=None) -> dict:
    """ROI, seeds and per-class found / covered / recovered figures of one seed set, against the operating
    point's."""
    rows = tally.rows
    base_found = np.array([r["cause"] == "found" for r in rows])
    classes = np.array([r["class_id"] for r in rows])
    op_roi = np.array(tally.roi["operating"])
    n_vox = np.array([r["n_voxels"] for r in rows], float)
    base_covered = np.array([r["roi_share"] >= 0.5 for r in rows])
    found = np.concatenate([np.asarray(f, bool) for f, _ in found_lists])
    share = np.concatenate([np.asarray(r, float) for _, r in found_lists])
    covered = share >= 0.5
    out = {"roi_voxels_mean": float(np.mean(roi)), "roi_voxels_ratio": float(np.sum(roi) / np.sum(op_roi)),
           "seeds_mean": float(np.mean(seeds)), "false_seeds_mean": float(np.mean(false_seeds)), "classes": {}}
    if compute_roi is not None:
        out["segmented_voxels_mean"] = float(np.mean(compute_roi))
        out["segmented_voxels_ratio"] = float(np.sum(compute_roi) / np.sum(op_roi))
    for cid, name in enumerate(class_names):
        if cid == 0:
            continue
        sel = classes == cid
        lost = sel & ~base_found
        out["classes"][name] = {
            "found_fraction": float(found[sel].mean()) if sel.any() else None,
            "covered_fraction": float(covered[sel].mean()) if sel.any() else None,
            "rg_recall": float((share[sel] * n_vox[sel]).sum() / n_vox[sel].sum()) if sel.any() else None,
            "lost_at_operating": int(lost.sum()),
            "recovered": int((lost & found).sum()),
            "recovered_fraction_of_lost": float((lost & found).sum() / lost.sum()) if lost.any() else None,
            "newly_lost": int((sel & base_found & ~found).sum()),
            "uncovered_at_operating": int((sel & ~base_covered).sum()),
            "covered_recovered": int((sel & ~base_covered & covered).sum()),
        }
    return out


def lost_cause_transitions(tally: StoreTally, class_names: list[str]) -> dict:
    """Per class, what the operating point's lost objects become at the lower threshold (global)."""
    low_causes = [c for w in tally.whatif["global"] for c in w["causes"]]
    transitions = {}
    for cid, name in enumerate(class_names):
        if cid == 0:
            continue
        table_c: dict[str, dict[str, int]] = {}
        for row, after in zip(tally.rows, low_causes, strict=True):
            if row["class_id"] == cid and row["cause"] != "found":
                cell = table_c.setdefault(row["cause"], {})
                cell[after] = cell.get(after, 0) + 1
        transitions[name] = table_c
    return transitions


def store_summary(tally: StoreTally, net, args, class_names: list[str]) -> dict:
    """The figures of one store but its name, frame count, timing, seed and detection scores."""
    rows, background, extra_kinds, low = tally.rows, tally.background, tally.extra_kinds, args.low_threshold
    sweeps = {f"{t:g}": whatif_summary(tally, class_names, tally.sweep[t], *zip(*tally.sweep_roi[t], strict=True))
              for t in SWEEP}
    whatifs = {name: whatif_summary(tally, class_names, [w["found"] for w in ws], [w["roi"] for w in ws],
                                    [w["seeds"] for w in ws], [w["false_seeds"] for w in ws],
                                    [w["compute_roi"] for w in ws] if name != "oracle_ped" else None)
               for name, ws in tally.whatif.items()}
    n_frames = tally.checked["frames"]
    return {
        "reproduced_operating_point": tally.checked,
        "roi_operating": {"roi_voxels_mean": float(np.array(tally.roi["operating"]).mean()),
                          "seeds_mean": float(np.mean(tally.roi["operating_seeds"])),
                          "false_seeds_mean": float(np.mean(tally.roi["operating_false_seeds"]))},
        "classes": class_table(rows, class_names, low, float(net.profile.doppler_bin(0.0))),
        "threshold_sweep": sweeps,
        "pedestrian_threshold_whatif": {"low_threshold": low, **whatifs,
                                        "lost_cause_transitions_global": lost_cause_transitions(tally, class_names),
                                        "extra_seeds_global": extra_kinds,
                                        "extra_seeds_per_frame": sum(extra_kinds.values()) / max(n_frames, 1)},
        "heatmap_background": {"median_mean": float(np.mean([b[0] for b in background])),
                               "q90_mean": float(np.mean([b[1] for b in background])),
                               "share_of_cells_above_floor": float(np.mean([b[2] for b in background]))},
        "objects_table": rows,
    }


def run_store(net, store: str, args, class_names: list[str], cells_xy, picture_pool: list) -> dict:
    root = open_store(store)
    if root.attrs["preset"] != net.profile.name:
        raise SystemExit(f"store {store} is preset {root.attrs['preset']}, the model {net.profile.name}")
    frames = frames_of_split(root, None)
    if args.frames:
        frames = frames[spread(len(frames), args.frames)]
    arrays = {name: root[name] for name in ("input", "instances", "objects", "n_objects")}
    earlier = earlier_slots(root, net.history_frames) if net.history_frames else None  # each frame's earlier ones
    ped = class_names.index("pedestrian")
    tally = StoreTally()
    scorer = DetectionScorer(net.profile)
    started = time.perf_counter()
    for number, slot in enumerate(frames):
        slot = int(slot)
        data = {name: a[slot] for name, a in arrays.items()}
        table = data["objects"][: int(data["n_objects"])].astype(np.float64)
        log_power = data["input"].astype(np.float32)
        history = None if earlier is None else earlier_frames(arrays["input"], earlier[slot])
        frame = Frame(net, log_power, data["instances"], table, args, cells_xy, history)
        scorer.add(take(frame.peaks, np.arange(min(len(frame.peaks), net.max_objects))), table)  # as evaluate
        regions, status = tally_operating(tally, net, frame, log_power, slot, store, ped, picture_pool)
        # what-ifs, each scored with the same rule
        tally_sweep(tally, frame, regions, status, net.score_threshold)
        tally_lower_threshold(tally, net, frame, log_power, args, class_names, ped)
        if args.progress and (number + 1) % 32 == 0:
            print(f"  {Path(store).name}: {number + 1}/{len(frames)} frames, {time.perf_counter() - started:.0f} s",
                  flush=True)
    summary = store_summary(tally, net, args, class_names)
    return {
        "store": store, "frames": int(len(frames)), "objects": len(tally.rows),
        "seconds": time.perf_counter() - started,
        "store_seed": root.attrs.get("job", {}).get("seed") if isinstance(root.attrs.get("job"), dict) else None,
        "reproduced_operating_point": summary.pop("reproduced_operating_point"),
        "detection": scorer.summary(),
        **summary,
    }


def pictures(net, args, class_names, picture_pool, results, cells_xy) -> list[str]:
    out_dir = Path(args.pictures_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    drawn = []
    # the most frequent causes first, one picture each, then a second of the most frequent
    counts: dict[str, int] = {}
    for *_, cause in picture_pool:
        counts[cause] = counts.get(cause, 0) + 1
    order = sorted(counts, key=lambda c: -counts[c])
    chosen, used = [], set()
    for cause in (order[:3] + order[:1]):
        pool = [p for p in picture_pool if p[3] == cause and (p[0], p[1]) not in used]
        if not pool or len(chosen) >= args.pictures:
            continue
        pick = pool[len(pool) // 2]  # a deterministic, middle-of-the-list example
        chosen.append(pick)
        used.add((pick[0], pick[1]))
    col = OBJECT_COLUMN
    for n, (store, slot, j, cause) in enumerate(chosen, start=1):
        root = open_store(store)
        n_obj = int(root["n_objects"][slot])
        table = root["objects"][slot][:n_obj].astype(np.float64)
        log_power = root["input"][slot].astype(np.float32)
        history = earlier_frames(root["input"], earlier_slots(root, net.history_frames)[slot]) \
            if net.history_frames else None
        frame = Frame(net, log_power, root["instances"][slot], table, args, cells_xy, history)
        result = net.segment(log_power, kind=InputKind.log_power, history=history)
        row = next(r for r in results[store]["objects_table"] if r["slot"] == slot and r["object"] == j)
        title = (f"{Path(store).name} frame {slot}: pedestrian at {row['range_m']:.1f} m, {row['n_voxels']} voxels, "
                 f"Doppler {table[j, col['doppler_bin']]:.1f}\ncause {cause}; heat {row['heat']:.2f}, "
                 f"best own peak {row['best_peak']:.2f}, ROI share {row['roi_share']:.2f}")
        path = out_dir / f"stage1_miss{n}_{cause}.png"
        draw_miss(frame, j, result.centres, result.regions, class_names, path, title)
        drawn.append(str(path))
    return drawn


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = None
    return {"cpu": cpu, "cpus": os.cpu_count(), "loadavg": list(os.getloadavg()), "python": sys.version.split()[0],
            "commit": commit}


def print_tables(results: dict, class_names: list[str], drawn: list[str]) -> None:
    for store, res in results.items():
        print(f"\n== {store}: {res['frames']} frames, {res['objects']} objects, {res['seconds']:.0f} s; "
              f"AP@1/3/5 {res['detection']['AP@1']:.3f}/{res['detection']['AP@3']:.3f}/"
              f"{res['detection']['AP@5']:.3f} mAP {res['detection']['mAP']:.3f}; operating point reproduced "
              f"{res['reproduced_operating_point']}")
        print(f"{'class':11} {'n':>4} {'found':>6} {'det@1':>6} {'det@3':>6} {'det@5':>6} " +
              " ".join(f"{c:>8}" for c in ("a", "b", "c", "d", "e")) + f" {'lostROI':>7} {'rg pred':>7} {'rg true':>7}")
        for name in class_names[1:]:
            c = res["classes"][name]
            n = max(c["count"], 1)
            print(f"{name:11} {c['count']:4d} {c['found_fraction'] or 0:6.3f} "
                  + " ".join(f"{c['detected_fraction'][k] or 0:6.3f}" for k in ("k1", "k3", "k5")) + " "
                  + " ".join(f"{c['letters'][x]:3d} {c['letters'][x] / n:4.2f}" for x in "abcde")
                  + f" {c['lost_with_voxels_in_roi']:7d} {c['rg_recall_predicted_seeds'] or 0:7.3f}"
                  f" {c['rg_recall_true_centres'] or 0:7.3f}")
        print("fine causes (count): " + "; ".join(
            f"{name}: " + ", ".join(f"{k}={v}" for k, v in res["classes"][name]["causes"].items() if v)
            for name in class_names[1:]))
        print("peak score quantiles (q10 q25 q50 q75 q90; share < 0.05, < 0.3):")
        for name in class_names[1:]:
            c = res["classes"][name]
            q = c["peak_score_quantiles"]
            print(f"  {name:11} " + " ".join(f"{v:.3f}" for v in q.values())
                  + f"; {c['peak_score_below_floor']:.3f}, {c['peak_score_below_threshold']:.3f}")
        print("lost objects whose voxels are >= 50 % in the ROI anyway, by cause: " + "; ".join(
            f"{name}: " + ", ".join(f"{k}={v}" for k, v in res["classes"][name]["lost_roi_covered_by_cause"].items()
                                   if v) for name in class_names[1:]))
        print("threshold sweep (global): t  found ped/cyc/car  covered ped/cyc/car  voxel recall ped/cyc/car"
              "  ROI voxels (x operating)  seeds  false seeds")
        for t, s in res["threshold_sweep"].items():
            print(f"  {t:>5} " + "/".join(f"{s['classes'][n]['found_fraction']:.3f}" for n in class_names[1:])
                  + "  " + "/".join(f"{s['classes'][n]['covered_fraction']:.3f}" for n in class_names[1:])
                  + "  " + "/".join(f"{s['classes'][n]['rg_recall']:.3f}" for n in class_names[1:])
                  + f"  {s['roi_voxels_mean']:8.0f} ({s['roi_voxels_ratio']:.2f})  {s['seeds_mean']:.2f}"
                  f"  {s['false_seeds_mean']:.2f}")
        w = res["pedestrian_threshold_whatif"]
        print(f"pedestrian what-if at {w['low_threshold']}: recovered / lost pedestrians, ROI voxels (x operating), "
              "segmented voxels, false seeds")
        for name in ("global", "oracle_ped", "gated_ped"):
            s = w[name]
            p = s["classes"]["pedestrian"]
            seg = (f"{s['segmented_voxels_mean']:.0f} ({s['segmented_voxels_ratio']:.2f})"
                   if "segmented_voxels_mean" in s else "-")
            print(f"  {name:10} {p['recovered']}/{p['lost_at_operating']} ({p['recovered_fraction_of_lost'] or 0:.3f}),"
                  f" newly lost {p['newly_lost']}; ROI-uncovered recovered {p['covered_recovered']}/"
                  f"{p['uncovered_at_operating']}; found {p['found_fraction']:.3f},"
                  f" covered {p['covered_fraction']:.3f}, ped voxel recall {p['rg_recall']:.3f};"
                  f" ROI {s['roi_voxels_mean']:.0f} ({s['roi_voxels_ratio']:.2f});"
                  f" segmented {seg}; false seeds {s['false_seeds_mean']:.2f}")
        print(f"  at {w['low_threshold']} (global), the operating point's lost objects become: " + "; ".join(
            f"{name}: " + ", ".join(f"{c}->{dict(sorted(v.items()))}"
                                   for c, v in w["lost_cause_transitions_global"][name].items())
            for name in class_names[1:]))
        print(f"  extra seeds in [{w['low_threshold']}, threshold) ({w['extra_seeds_per_frame']:.2f} per frame): "
              + ", ".join(f"{k}={v}" for k, v in sorted(w["extra_seeds_global"].items())))
        print("  (b) pedestrians' own best peak: " + " ".join(
            f"{k} {v:.3f}" for k, v in res["classes"]["pedestrian"]["b_best_peak_quantiles"].items())
            + f"; {res['classes']['pedestrian']['b_best_peak_at_least_low']} of "
            f"{res['classes']['pedestrian']['causes']['b_below_threshold']} at least {w['low_threshold']}")
        for name in class_names[1:]:
            for stratum, cells in res["classes"][name]["strata"].items():
                print(f"  {name} by {stratum}: " + "; ".join(
                    f"[{c['from']:g}, {'inf' if c['to'] is None else format(c['to'], 'g')}) n={c['count']}"
                    + (f" peak {c['peak_median']:.2f} found {c['found_fraction']:.2f}"
                       f" det {c['detected_fraction_k3']:.2f}" if c["count"] else "") for c in cells))
        hb = res["heatmap_background"]
        print(f"  heatmap background: median {hb['median_mean']:.3f}, q90 {hb['q90_mean']:.3f}, "
              f"cells >= floor {hb['share_of_cells_above_floor']:.3f}")
    if drawn:
        print("\npictures: " + ", ".join(drawn))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", action="append", required=True, help="preprocessed store (repeat for several)")
    parser.add_argument("--frames", type=int, default=0, help="frames per store, evenly spread (0 = all)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", default="experiments/reports/stage1.json", help="JSON written here")
    parser.add_argument("--detector", default="checkpoints/detector.pt")
    parser.add_argument("--segmenter", default="checkpoints/segmenter.pt")
    parser.add_argument("--match-k", type=float, default=3.0, help="match radius: metres and Doppler bins")
    parser.add_argument("--floor", type=float, default=0.05, help="heatmap floor of cause (a)")
    parser.add_argument("--min-share", type=float, default=0.5, help="share of an object's voxels its seed must grow")
    parser.add_argument("--low-threshold", type=float, default=0.15, help="pedestrian threshold of the what-if")
    parser.add_argument("--peaks", type=int, default=256, help="heatmap peaks decoded for the diagnosis")
    parser.add_argument("--pictures", type=int, default=3, help="pictures of pedestrian misses")
    parser.add_argument("--pictures-dir", default="experiments/reports")
    parser.add_argument("--no-progress", dest="progress", action="store_false")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    info = {"machine_start": machine()}
    net = EraseNet.from_checkpoints(load_checkpoint(args.detector, stage="detector", option="--detector"),
                                         load_checkpoint(args.segmenter, stage="segmenter", option="--segmenter"))
    freeze_loaded_heap()
    class_names = list(open_store(args.store[0]).attrs["class_names"])
    if tuple(class_names) != tuple(net.class_names):
        raise SystemExit(f"store classes {class_names} differ from the model's {net.class_names}")
    stride = 4
    h, w = -(-net.profile.n_range // stride), -(-net.profile.n_angle // stride)
    cells_xy = net.profile.xy(((np.arange(h) + 0.5) * stride - 0.5)[:, None],
                              ((np.arange(w) + 0.5) * stride - 0.5)[None])
    results, pool = {}, []
    for store in args.store:
        results[store] = run_store(net, store, args, class_names, cells_xy, pool)
    drawn = pictures(net, args, class_names, pool, results, cells_xy) if args.pictures else []
    if args.pictures:
        hist_path = Path(args.pictures_dir) / "stage1_peak_scores.png"
        draw_histograms(results, class_names, hist_path)
        drawn.append(str(hist_path))
    print_tables(results, class_names, drawn)
    out = {
        "what": "issue 34 point 1: where true objects are lost between the detector and region growing",
        "command": " ".join([".venv/bin/python -m experiments.studies.stage1_diagnosis", *(argv or sys.argv[1:])]),
        "args": vars(args), "classes": class_names, "score_threshold": net.score_threshold,
        "region_growing": asdict(net.region_config),
        "doppler_refinement": None if net.doppler_refinement is None else asdict(net.doppler_refinement),
        "ap_score_threshold": AP_SCORE_THRESHOLD, "causes": list(CAUSES), "histogram_edges": HIST_EDGES.tolist(),
        "threads": torch.get_num_threads(), "torch": torch.__version__,
        **info, "machine_end": machine(), "seconds": time.perf_counter() - started,
        "pictures": drawn, "stores": results,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1, default=float))
    print(f"written to {args.out} ({out['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
