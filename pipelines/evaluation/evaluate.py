"""Evaluation of a trained ERASE-Net on a split of a store (docs/design.md sections 6, 10 and 12).

``radarseg evaluate --detector CKPT --segmenter CKPT --store STORE --split test --out DIR`` (or
``python -m pipelines.evaluation.evaluate ...``) runs :class:`models.erasenet.model.EraseNet` on every frame of the
split and writes ``DIR/metrics.json``, ``DIR/report.md`` (:mod:`pipelines.evaluation.report`) and pictures:

- detection: AP at k = 1, 3, 5 (metres and Doppler bins) and mAP (:mod:`radar.metrics`). The detector
  is decoded for AP down to a score of ``AP_SCORE_THRESHOLD`` (a full precision-recall curve); the
  segmentation runs at the network's operating threshold (``--score-threshold``);
- region growing: recall (ground-truth object voxels inside the ROI over all of them, pooled over the
  split) and visited points from the predicted seeds and from the ground-truth centres, plus a
  D_thresh sweep for both on up to ``--sweep-frames`` frames;
- segmentation: one RA and one RD confusion matrix over the split (background included), IoU per
  class and mIoU; the same with true centres (stage 2 alone, "oracle seeds");
- cost: parameters and MACs per stage (mean per frame), seconds per stage (mean per frame);
- tracking: the tracker (radar.tracking) per sequence over the predicted objects and over the true centres,
  CLEAR MOT / identity metrics and velocity errors against the simulator's tracks
  (:mod:`pipelines.evaluation.tracking`); a store without tracking truth gets a one-line reason instead. With
  ``--trackers`` the named trackers (ours, Stone Soup's) run on the same objects and are scored with GOSPA, HOTA,
  MOTA / IDF1 and velocity error (:mod:`pipelines.evaluation.tracker_comparison`, ``tracking.trackers``);
- pictures: PR curves, the RA/RD confusion matrices, and RA/RD maps of ``--pictures`` frames with the
  ground truth above the prediction.

Figures in ``metrics.json`` are fractions (IoU, recall, AP in [0, 1]); the report prints IoU in %. The options and
the config are in :mod:`pipelines.evaluation.evaluate_options`.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.capabilities import Stage
from models.checkpoint import load_checkpoint
from models.erasenet.model import EraseNet
from models.heap import freeze_loaded_heap
from models.runtime import Runtime, load_erasenet
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.spread import spread
from pipelines.datasets.store import (
    CENTRE_COLUMNS,
    OBJECT_COLUMN,
    frames_of_split,
    open_store,
    tracking_truth_problem,
)
from pipelines.evaluation.evaluate_options import (  # noqa: F401 (the job's options: pipelines.jobs' contract)
    EvaluateConfig,
    add_arguments,
    config_from_args,
)
from pipelines.evaluation.report import tracking_headline
from pipelines.evaluation.scoring import DetectionScorer, ViewConfusion
from pipelines.evaluation.tracker_comparison import (
    compare_trackers,
    plot_gospa_by_frame,
    save_frames,
)
from pipelines.evaluation.tracking import TrackingTally, by_sequence
from pipelines.jobs import run_module
from pipelines.progress import progress
from radar.centres import Centres
from radar.doppler import DOPPLER_REFINEMENT
from radar.errors import UserError
from radar.input_kind import InputKind
from radar.region_growing import RegionGrowingConfig, grow_regions
from radar.track_priors import SequenceTracks, TrackPriors, TrackPriorsConfig
from radar.tracking import TrackerConfig

log = logging.getLogger(__name__)

AP_SCORE_THRESHOLD = 0.01  # detections kept for the PR curve
LATER_FROM = 2  # frames_with_history scores a sequence's frames from this frame index on


def _int8_calibration(store: str, profile: Any) -> Any:
    """Calibration frames of the int8 segmenter: the store's train split, or simulated frames where it has none."""
    from models.export.export_cache import Int8Calibration
    from pipelines.datasets.calibration import store_calibration

    try:
        return store_calibration(store, profile)
    except ValueError as error:
        log.warning("int8 calibration on simulated frames: %s", error)
        return Int8Calibration.simulated(profile)


class _RecallCounter:
    """Pooled region-growing recall and mean visited points / ROI voxels over frames."""

    def __init__(self) -> None:
        self.inside = self.truth = self.visited = self.roi = self.frames = 0

    def add(self, regions, instances: np.ndarray) -> None:
        self.truth += int(np.count_nonzero(instances))
        self.inside += int(np.count_nonzero(instances[tuple(regions.voxels.T)])) if len(regions) else 0
        self.visited += regions.visited
        self.roi += len(regions)
        self.frames += 1

    def summary(self) -> dict[str, float]:
        frames = max(self.frames, 1)
        return {"recall": self.inside / self.truth if self.truth else float("nan"),
                "visited_mean": self.visited / frames, "roi_voxels_mean": self.roi / frames, "frames": self.frames}


@dataclass
class _Tallies:
    """Everything :func:`evaluate` sums over the frames."""

    detection: DetectionScorer
    confusion: ViewConfusion
    oracle_confusion: ViewConfusion
    sweep: dict[tuple[str, float], _RecallCounter]
    predicted_seeds: _RecallCounter = field(default_factory=_RecallCounter)
    # frames with history: the frames of a sequence after its first LATER_FROM (what tracks can help)
    later_confusion: ViewConfusion | None = None
    later_seeds: _RecallCounter = field(default_factory=_RecallCounter)
    prior_seeds: int = 0
    truth_seeds: _RecallCounter = field(default_factory=_RecallCounter)
    macs: dict[str, list[float]] = field(default_factory=dict)
    seconds: dict[str, list[float]] = field(default_factory=dict)

    @classmethod
    def empty(cls, profile: Any, distances: tuple[float, ...]) -> _Tallies:
        num_classes = profile.num_classes
        return cls(DetectionScorer(profile), ViewConfusion(num_classes), ViewConfusion(num_classes),
                   {(seeds, d): _RecallCounter() for seeds in ("predicted", "truth") for d in distances},
                   later_confusion=ViewConfusion(num_classes))


def evaluate(cfg: EvaluateConfig) -> dict[str, Any]:
    """Run the evaluation; writes ``metrics.json``, ``report.md`` and pictures into ``cfg.out``; returns the metrics."""
    from pipelines.evaluation.report import write_report

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    det_ckpt = load_checkpoint(cfg.detector, stage=Stage.DETECTOR, option="--detector")
    seg_ckpt = load_checkpoint(cfg.segmenter, stage=Stage.SEGMENTER, option="--segmenter")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    kwargs: dict[str, Any] = {} if cfg.score_threshold is None else {"score_threshold": cfg.score_threshold}
    kwargs["doppler_refinement"] = DOPPLER_REFINEMENT if cfg.doppler_refinement else None
    runtime = Runtime.parse(cfg.runtime)
    if runtime.backend == "torch":
        kwargs["device"] = cfg.device
    elif cfg.onnx_dir is not None:
        kwargs["onnx_dir"] = cfg.onnx_dir
    if runtime == Runtime("torch", "int8"):  # calibrated on the store's train split, as the int8 export is given one
        kwargs["calibration"] = _int8_calibration(cfg.store, det_ckpt.profile)
    net = load_erasenet(det_ckpt, seg_ckpt, runtime, **kwargs)
    freeze_loaded_heap()  # no full garbage collection over torch and the models every few frames
    root, frames = store_frames(cfg.store, net.profile, cfg.split, cfg.max_frames)
    split_name = cfg.split or "all"
    arrays = {name: root[name] for name in ("input", "instances", "ra_mask", "rd_mask", "objects", "n_objects")}
    picture_frames = {int(frames[i]) for i in spread(len(frames), cfg.pictures)}
    sweep_frames = {int(frames[i]) for i in spread(len(frames), cfg.sweep_frames)}
    tallies = _Tallies.empty(net.profile, cfg.sweep)
    tracking = TrackingTally(net.profile, tracking_truth_problem(root, cfg.store))
    if tracking.problem:
        log.warning("tracking not evaluated: %s", tracking.problem)
    sequence_ids, frame_indices = root["sequence_id"][:], root["frame_index"][:]
    history_frames = 0 if cfg.single_cube else net.history_frames
    earlier = earlier_slots(root, history_frames) if history_frames else None
    sequence_tracks = None
    if cfg.track_priors is not None:  # each sequence's frames in order: its tracks predict the next one
        priors_config = TrackPriorsConfig(cfg.track_priors, cfg.track_priors_gate_m)
        sequence_tracks = SequenceTracks(TrackerConfig.for_profile(net.profile), priors_config)
        frames = frames[np.lexsort((frame_indices[frames], sequence_ids[frames]))]
    pictures: list[str] = []
    started = time.perf_counter()
    for slot in progress(frames, desc=f"evaluate {split_name}", unit="frame", disable=not cfg.progress):
        slot = int(slot)
        sequence, index = int(sequence_ids[slot]), int(frame_indices[slot])
        frame = {name: array[slot] for name, array in arrays.items()}
        history = None if earlier is None else earlier_frames(arrays["input"], earlier[slot])
        priors = None if sequence_tracks is None else sequence_tracks.priors(sequence, index)
        picture = _score_frame(net, cfg, tallies, frame, in_sweep=slot in sweep_frames, history=history,
                               priors=priors, later=index >= LATER_FROM)
        if sequence_tracks is not None:
            sequence_tracks.step(sequence, index, picture[3].objects)
        tracking.add(sequence, index, picture[2], picture[3].objects)
        if slot in picture_frames:
            title = f"{split_name} frame {slot}: ground truth (top) / prediction (bottom)"
            pictures.append(_frame_picture(net, picture, out / f"frame_{slot:05d}.png", title=title))
    pictures = _summary_pictures(tallies, net.class_names, out, f"{split_name}, {len(frames)} frames") + pictures
    metrics = _metrics(cfg, net, (det_ckpt, seg_ckpt), tallies, split_name, len(frames))
    metrics.update(seconds=time.perf_counter() - started, pictures=pictures)  # in their place among the keys
    metrics["history_frames"] = history_frames
    if cfg.oracle:
        metrics["segmentation_truth_seeds"] = {view.upper(): summary for view, summary
                                               in tallies.oracle_confusion.summary(net.class_names).items()}
    metrics["tracking"] = tracking.summary(TrackerConfig.for_profile(net.profile))
    if cfg.trackers and tracking.problem is None:
        _compare_trackers(cfg.trackers, tracking, net, metrics, out)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    write_report(metrics, out / "report.md")
    return metrics


def _compare_trackers(names: tuple[str, ...], tracking: TrackingTally, net: EraseNet, metrics: dict[str, Any],
                      out: Path) -> None:
    """Trackers ``names`` on the tracked objects: ``tracking.trackers`` in ``metrics``, the GOSPA plot, and the
    objects in ``tracking_frames.npz`` (to compare or tune trackers again without the network:
    ``python -m experiments.studies.stonesoup_tuning``)."""
    save_frames(tracking.frames, out / "tracking_frames.npz")  # first: the network's work is kept whatever follows
    metrics["tracking"]["trackers"] = compare_trackers(by_sequence(tracking.frames), names,
                                                       TrackerConfig.for_profile(net.profile), net.class_names,
                                                       metrics["tracking"]["match_distance_m"])
    metrics["pictures"].append(plot_gospa_by_frame(metrics["tracking"]["trackers"], out / "tracking_gospa.png"))


def store_frames(store: str | Path, profile: Any, split: str | None, max_frames: int = 0) -> tuple[Any, np.ndarray]:
    """The store (checked against the model's preset) and the slots of ``split`` to score (``max_frames`` evenly
    spread, 0: all; None: every frame of the store)."""
    root = open_store(store)
    if root.attrs["preset"] != profile.name:
        raise UserError(f"store {store} is preset {root.attrs['preset']!r}, the model {profile.name!r}")
    frames = frames_of_split(root, split)
    if max_frames:
        frames = frames[spread(len(frames), max_frames)]
    if len(frames) == 0:
        raise UserError(f"split {split!r} of {store} has no frames")
    return root, frames


def _score_frame(net: EraseNet, cfg: EvaluateConfig, tallies: _Tallies, frame: dict[str, np.ndarray], *,
                 in_sweep: bool, history: list[np.ndarray | None] | None = None, priors: TrackPriors | None = None,
                 later: bool = False) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, Any]:
    """Add one frame to every tally (``history``: its earlier frames' log power, for a detector that reads them;
    ``priors``: its sequence's tracks' predictions; ``later``: a frame with history, scored in
    ``frames_with_history`` too); returns what its picture needs: log power, truth masks, object table, the
    segmentation result."""
    profile = net.profile
    log_power = frame["input"].astype(np.float32)  # (R, A, D) dB
    instances = frame["instances"]
    truth = {"ra": frame["ra_mask"], "rd": frame["rd_mask"]}
    table = frame["objects"][: int(frame["n_objects"])].astype(np.float64)

    # detection AP: the scored centres of the engine's own detector (the ONNX graph on the ONNX engines) down to a
    # low threshold, Doppler refined as the product refines it: AP of what it outputs
    scored = net.detect(log_power, score_threshold=AP_SCORE_THRESHOLD, history=history)
    tallies.detection.add(scored, table)

    # the whole chain at the operating threshold
    result = net.segment(log_power, kind=InputKind.log_power, history=history, priors=priors)
    tallies.confusion.add_masks(truth, result.ra_mask, result.rd_mask)
    tallies.predicted_seeds.add(result.regions, instances)
    tallies.prior_seeds += result.prior_seeds
    if later:
        tallies.later_confusion.add_masks(truth, result.ra_mask, result.rd_mask)
        tallies.later_seeds.add(result.regions, instances)
    for name, value in result.compute.macs_by_stage().items():
        tallies.macs.setdefault(name, []).append(value)
    for name, value in result.compute.seconds_by_stage().items():
        tallies.seconds.setdefault(name, []).append(value)

    truth_centres = Centres.from_bins(table[:, CENTRE_COLUMNS])
    tallies.truth_seeds.add(grow_regions(log_power, truth_centres, profile, net.region_config), instances)
    if cfg.oracle:
        oracle = net.segment(log_power, kind=InputKind.log_power, centres=truth_centres)
        tallies.oracle_confusion.add_masks(truth, oracle.ra_mask, oracle.rd_mask)
    if in_sweep:
        for (seeds, distance), counter in tallies.sweep.items():
            config = RegionGrowingConfig(**{**asdict(net.region_config), "distance_m": distance})
            centres = result.centres if seeds == "predicted" else truth_centres
            counter.add(grow_regions(log_power, centres, profile, config), instances)
    return log_power, truth, table, result


def _frame_picture(net: EraseNet, picture: tuple, path: Path, *, title: str) -> str:
    """Ground truth against prediction for one frame, objects annotated; the file's name."""
    from pipelines.figures import plot_truth_vs_prediction

    log_power, truth, table, result = picture
    profile, col = net.profile, OBJECT_COLUMN
    truth_notes = [(net.class_names[int(row[col["class_id"]])], row[col["x"]], row[col["y"]],
                    float(profile.velocity_mps(row[col["doppler_bin"]]))) for row in table]
    pred_notes = [(f"{o.class_name} {o.score:.2f}", o.x, o.y, o.velocity_mps) for o in result.objects]
    return plot_truth_vs_prediction(log_power, profile, (truth["ra"], truth["rd"]), (result.ra_mask, result.rd_mask),
                                    path, truth_objects=truth_notes, predicted_objects=pred_notes, title=title).name


def _summary_pictures(tallies: _Tallies, class_names: Any, out: Path, what: str) -> list[str]:
    """The PR curves and one confusion matrix per view."""
    from pipelines.figures import plot_confusion, plot_pr_curves

    curves = tallies.detection.curves()
    legend = {f"k = {k:g} (m and Doppler bins)": (c.recall, c.precision, c.ap) for k, c in curves.items()}
    names = [plot_pr_curves(legend, out / "pr_curves.png").name]
    for view, matrix in tallies.confusion.matrices.items():
        names.append(plot_confusion(matrix, class_names, out / f"confusion_{view}.png",
                                    title=f"{view.upper()} confusion ({what})").name)
    return names


def _metrics(cfg: EvaluateConfig, net: EraseNet, checkpoints: tuple[Any, Any], tallies: _Tallies, split_name: str,
             n_frames: int) -> dict[str, Any]:
    """metrics.json but for the figures only the caller knows: ``seconds``, ``pictures`` (placeholders here)
    and ``segmentation_truth_seeds``."""
    det_ckpt, seg_ckpt = checkpoints
    class_names, detection = net.class_names, tallies.detection
    curves = detection.curves()
    return {
        "store": str(cfg.store), "out": str(cfg.out), "split": split_name, "frames": n_frames,
        "preset": net.profile.name,
        "detector": str(cfg.detector), "segmenter": str(cfg.segmenter),
        "models": {"detector": det_ckpt.model_name, "segmenter": seg_ckpt.model_name},
        "training": {"detector": _training_info(det_ckpt.extra), "segmenter": _training_info(seg_ckpt.extra)},
        "score_threshold": net.score_threshold, "classes": list(class_names),
        "doppler_refinement": None if net.doppler_refinement is None else asdict(net.doppler_refinement),
        "detection": {**detection.summary(), **detection.thresholds(), "n_truth": detection.n_truth,
                      "n_predictions": int(len(next(iter(curves.values())).score)) if curves else 0,
                      "ap_score_threshold": AP_SCORE_THRESHOLD},
        "region_growing": {
            "config": asdict(net.region_config),
            "predicted_seeds": tallies.predicted_seeds.summary(), "truth_seeds": tallies.truth_seeds.summary(),
            "sweep": [{"seeds": seeds, "distance_m": d, **counter.summary()}
                      for (seeds, d), counter in tallies.sweep.items()],
        },
        "segmentation": {view.upper(): summary for view, summary in tallies.confusion.summary(class_names).items()},
        "frames_with_history": {
            "from_frame_index": LATER_FROM, "frames": tallies.later_seeds.frames,
            "region_growing_recall": tallies.later_seeds.summary()["recall"],
            "segmentation": {view.upper(): summary
                             for view, summary in tallies.later_confusion.summary(class_names).items()}},
        "track_priors": None if cfg.track_priors is None else {
            "threshold": cfg.track_priors, "gate_m": cfg.track_priors_gate_m, "seeds_added": tallies.prior_seeds},
        "cost": {"params": net.params | {"total": sum(net.params.values())},
                 "macs_mean": {k: float(np.mean(v)) for k, v in tallies.macs.items()},
                 "seconds_mean": {k: float(np.mean(v)) for k, v in tallies.seconds.items()}},
        "seconds": 0.0,
        "pictures": [],
    }


def _training_info(extra: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint says about its training (recipe, epochs, steps, time, validation figures; checkpoints
    written before the recipe had its name call it "profile")."""
    metrics = extra.get("metrics", {})
    return {"stage": extra.get("stage"), "recipe": extra.get("recipe", extra.get("profile")),
            "epoch": extra.get("epoch"), "step": extra.get("step"), "elapsed_s": metrics.get("elapsed_s"),
            **{k: v for k, v in metrics.items() if k.startswith("val_")}}


def main(cfg: EvaluateConfig) -> dict[str, Any]:
    """Run the evaluation (:func:`evaluate`); returns its metrics."""
    return evaluate(cfg)


def format_result(metrics: dict[str, Any]) -> str:
    return f"{format_summary(metrics)}\nreport: {metrics['out']}/report.md"


def format_summary(metrics: dict[str, Any]) -> str:
    """A few lines with the headline figures of :func:`evaluate`'s metrics."""
    det, rg, seg = metrics["detection"], metrics["region_growing"], metrics["segmentation"]
    return "\n".join([
        f"{metrics['split']}: {metrics['frames']} frames of {metrics['store']}",
        f"  detection AP@1 {det['AP@1']:.3f}  AP@3 {det['AP@3']:.3f}  AP@5 {det['AP@5']:.3f}  mAP {det['mAP']:.3f}"
        + (f"  ({det['thresholds']})" if "thresholds" in det else ""),
        f"  region growing recall {rg['predicted_seeds']['recall']:.3f} (predicted seeds), "
        f"{rg['truth_seeds']['recall']:.3f} (true centres); visited {rg['predicted_seeds']['visited_mean']:.0f}",
        f"  mIoU RA {100 * seg['RA']['mIoU']:.2f}  RD {100 * seg['RD']['mIoU']:.2f}",
        f"  {tracking_headline(metrics.get('tracking'))}",
    ])


if __name__ == "__main__":
    sys.exit(run_module("pipelines.evaluation.evaluate"))
