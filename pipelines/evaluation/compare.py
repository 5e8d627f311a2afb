"""ERASE-Net and the 2-D baselines side by side on the same frames (docs/design.md sections 9, 10 and 12).

The job follows :mod:`pipelines.jobs` (``add_arguments``, ``config_from_args``, ``main(cfg) -> dict``; the options
and the config in :mod:`pipelines.evaluation.compare_options`)::

    radarseg compare --store S.zarr --split test --out DIR \\
        --erasenet "ERASE-Net (M)=checkpoints/detector.pt,checkpoints/segmenter.pt" \\
        --baseline "U-Net=unet_rd.pt,unet_ra.pt" --baseline TMVA-Net=tmva.pt --baseline SMVA-Net=smva.pt \\
        [--cfar-segmenter [NAME=]SEG.pt] [--max-frames N] [--pictures K] [--threads N]

``--erasenet NAME=DETECTOR,SEGMENTER`` and ``--baseline NAME=CKPT`` repeat. A U-Net segments one view, so
a U-Net row is a pair ``NAME=RD_CKPT,RA_CKPT`` (either order; each checkpoint says its view): its RD mask
comes from the RD network and its RA mask from the RA one. ``--cfar-segmenter`` adds ERASE-Net with
:func:`radar.cfar.cfar_centres` in place of the learned detector (CFAR + region growing + segmenter).

Frames: every model is scored on the same target frames, those the longest-window model can use
(:func:`pipelines.datasets.views.split_windows`: TMVA-Net reads the target and the 4 frames before it in its
sequence, so the first 4 frames of each sequence are left out for every model), then ``--max-frames``
of them evenly spread.

Per model and view (RA, RD): one confusion matrix over the frames (background included), IoU per class
and mIoU (:mod:`radar.metrics`); params; MACs per frame by the correct counter and by the paper's
(:mod:`models.compute`: the paper's overcounts transposed convs; ERASE-Net's are the mean per frame of
detector + segmenter, the segmenter's from the ROI it saw, CFAR counted as 0); RA/RD consistency per
class and of occupancy (:func:`consistency_counts`); seconds per frame, wall clock on this CPU in this
run with ``--threads`` torch threads, from the log-power cube in memory (ERASE-Net: :meth:`EraseNet.segment`,
CFAR included) or from the prepared views (baselines: forward and argmax), store reads excluded.

Writes ``DIR/compare.json``, ``DIR/compare.md`` (:func:`render_compare`) and ``DIR/compare_frames.png``
(the same ``--pictures`` frames, ground truth first, then every model; RA and RD).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from models.capabilities import Stage, dense_input_shapes
from models.checkpoint import Checkpoint, load_checkpoint, load_pair
from models.compute import count_macs, count_params
from models.erasenet.model import EraseNet
from models.runtime import load_erasenet
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.spread import spread
from pipelines.datasets.store import open_store
from pipelines.datasets.store_info import StoreInfo
from pipelines.datasets.views import (
    ViewDataset,
    ViewStats,
    collate_views,
    load_baseline,
    model_inputs,
    scored_frames,
    split_windows,
)
from pipelines.evaluation.compare_options import (  # noqa: F401 (the job's options: pipelines.jobs' contract)
    CFAR_NAME,
    CompareConfig,
    Entry,
    ModelSpec,
    add_arguments,
    config_from_args,
    parse_model,
)
from pipelines.evaluation.report import fmt_num, fmt_pct, md_table
from pipelines.evaluation.scoring import ViewConfusion, predicted_views, view_summary
from pipelines.jobs import run_module
from pipelines.progress import progress
from radar.cfar import cfar_centres
from radar.errors import UserError
from radar.input_kind import InputKind
from radar.metrics import consistency, consistency_counts

log = logging.getLogger(__name__)

VIEWS = ("RD", "RA")  # the paper's column order
PAPER_CARRADA = {  # docs/design.md section 12: mIoU % RD / RA, MACs G (paper's counter); other data, for context only
    "U-Net": ("58.01", "30.42", "54.84 RD / 13.71 RA"), "TMVA-Net": ("57.03", "37.86", "102.35"),
    "SMVA-Net": ("56.39", "38.17", "72.35"), "ERASE-Net (M)": ("53.57", "43.95", "8.41 + 0.49"),
}


# --------------------------------------------------------------------------- predictors
@dataclass
class Prediction:
    ra_mask: np.ndarray  # (R, A)
    rd_mask: np.ndarray  # (R, D)
    seconds: float
    macs: float
    macs_paper: float


def _check_checkpoint(checkpoint: Checkpoint, path: str, preset: str, class_names: Sequence[str]) -> None:
    """UserError unless the checkpoint (its stage checked where it was loaded) is for the store's radar and classes."""
    if checkpoint.preset != preset:
        raise UserError(f"{path}: the model is for preset {checkpoint.preset!r}, the store is {preset!r}")
    if tuple(checkpoint.class_names) != tuple(class_names):
        raise UserError(f"{path}: classes {list(checkpoint.class_names)}, the store's {list(class_names)}")


class EraseNetPredictor:
    """ERASE-Net end to end, or (``cfar``) its segmenter behind CFAR seeds. Reads one frame's log power, and the
    earlier frames of its sequence from the store when the detector reads history (``n_frames`` 1 + history)."""

    n_frames = 1

    def __init__(self, spec: ModelSpec, preset: str, class_names: Sequence[str], *, device: str = "cpu",
                 score_threshold: float | None = None) -> None:
        self.spec = spec
        kwargs = {} if score_threshold is None else {"score_threshold": score_threshold}
        if spec.kind is Entry.ERASENET:
            det, seg = load_pair(*spec.checkpoints)
            _check_checkpoint(det, spec.checkpoints[0], preset, class_names)
            _check_checkpoint(seg, spec.checkpoints[1], preset, class_names)
            self.net = load_erasenet(det, seg, device=device, **kwargs)
            r, a, d = self.net.profile.shape
            detector = count_macs(self.net.detector, (1, d, r, a))
            self.paper_extra = detector.macs_paper - detector.macs  # per frame, the detector always runs
        else:
            seg = load_checkpoint(spec.checkpoints[0], stage=Stage.SEGMENTER)
            _check_checkpoint(seg, spec.checkpoints[0], preset, class_names)
            profile = seg.profile
            # No detector: CFAR gives the centres of every frame.
            self.net = EraseNet(None, seg.build(), profile, class_names=seg.class_names,
                                mean_db=seg.normalisation.get("mean", 0.0), std_db=seg.normalisation.get("std", 1.0),
                                device=device, **kwargs)
            self.paper_extra = 0
        self.params = sum(self.net.params.values())
        self.n_frames = 1 + self.net.history_frames
        self._inputs, self._earlier = None, None  # a history detector's store input and earlier slots (bind)
        self.macs_note = ("mean per frame, detector + segmenter (ROI-dependent)" if spec.kind is Entry.ERASENET
                          else "mean per frame, segmenter only (CFAR not counted)")

    def bind(self, store: str, split: str | None, targets: np.ndarray) -> None:
        """A detector that reads history finds each frame's earlier ones in the store; otherwise nothing to do."""
        if self.net.history_frames:
            root = open_store(store)
            self._inputs, self._earlier = root["input"], earlier_slots(root, self.net.history_frames)

    def __call__(self, slot: int, log_power: np.ndarray) -> Prediction:
        started = time.perf_counter()
        centres = cfar_centres(log_power, self.net.profile) if self.spec.kind is Entry.CFAR else None
        history = None if self._earlier is None else earlier_frames(self._inputs, self._earlier[slot])
        result = self.net.segment(log_power, kind=InputKind.log_power, centres=centres, history=history)
        seconds = time.perf_counter() - started
        macs = float(result.compute.macs_total)
        return Prediction(result.ra_mask, result.rd_mask, seconds, macs, macs + self.paper_extra)


class BaselinePredictor:
    """A multi-view baseline (TMVA-Net, SMVA-Net) or a U-Net pair (one network per view)."""

    def __init__(self, spec: ModelSpec, preset: str, class_names: Sequence[str], *, device: str = "cpu") -> None:
        self.spec = spec
        self.device = device
        self.models: list[tuple[nn.Module, ViewStats]] = []  # (network, its view scaling)
        for path in spec.checkpoints:
            model, checkpoint, stats = load_baseline(path, device=device)  # ValueError if not a baseline
            _check_checkpoint(checkpoint, path, preset, class_names)  # its stage checked by load_baseline
            self.models.append((model, stats))
        views = [view for model, _ in self.models for view in predicted_views(model)]
        if sorted(views) != ["ra", "rd"]:
            kinds = ", ".join(f"{path} ({'/'.join(predicted_views(model))})"
                              for path, (model, _) in zip(spec.checkpoints, self.models, strict=True))
            raise UserError(f"{spec.name!r}: expected one network predicting RD and RA (TMVA-Net, SMVA-Net) or a "
                             f"U-Net pair NAME=RD.pt,RA.pt (one per view), got {kinds}")
        self.n_frames = max(model.n_frames for model, _ in self.models)
        self.params = sum(count_params(model) for model, _ in self.models)
        reports = [count_macs(model, *dense_input_shapes(model, preset)) for model, _ in self.models]
        self.macs = float(sum(r.macs for r in reports))
        self.macs_paper = float(sum(r.macs_paper for r in reports))
        self.macs_note = "analytic per frame" + (" (RD + RA networks)" if len(self.models) > 1 else "")
        self.datasets: list[ViewDataset] = []
        self.index: dict[int, int] = {}

    def bind(self, store: str, split: str | None, targets: np.ndarray) -> None:
        """One dataset per network over the windows that end at ``targets``."""
        self.datasets = [ViewDataset(store, split, n_frames=model.n_frames, stats=stats, targets=targets)
                         for model, stats in self.models]
        for dataset in self.datasets:
            if not np.array_equal(dataset.windows[:, -1], targets):
                raise ValueError(f"{self.spec.name!r}: its windows do not end at the common target frames")
        self.index = {int(slot): i for i, slot in enumerate(targets)}

    @torch.no_grad()
    def __call__(self, slot: int, log_power: np.ndarray) -> Prediction:
        masks: dict[str, np.ndarray] = {}
        seconds = 0.0
        for (model, _), dataset in zip(self.models, self.datasets, strict=True):
            batch = collate_views([dataset[self.index[slot]]])
            started = time.perf_counter()
            outputs = model(*model_inputs(model, batch, self.device))
            for view in predicted_views(model):
                masks[view] = outputs[view].argmax(1)[0].cpu().numpy().astype(np.uint8)
            seconds += time.perf_counter() - started
        return Prediction(masks["ra"], masks["rd"], seconds, self.macs, self.macs_paper)


def build_predictor(spec: ModelSpec, preset: str, class_names: Sequence[str],
                    cfg: CompareConfig) -> EraseNetPredictor | BaselinePredictor:
    if spec.kind is Entry.BASELINE:
        return BaselinePredictor(spec, preset, class_names, device=cfg.device)
    return EraseNetPredictor(spec, preset, class_names, device=cfg.device, score_threshold=cfg.score_threshold)


@dataclass
class _Tally:
    """One model's sums over the frames."""

    num_classes: int
    confusion: ViewConfusion = field(init=False)
    inconsistent: int = 0  # (range, class) pairs present in one view only, summed over frames
    present: int = 0  # ... present in either view
    occupancy_inconsistent: int = 0  # the same with all object classes merged
    occupancy_present: int = 0
    seconds: list[float] = field(default_factory=list)
    macs: list[float] = field(default_factory=list)
    macs_paper: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.confusion = ViewConfusion(self.num_classes)

    def add(self, truth: dict[str, np.ndarray], ra_mask: np.ndarray, rd_mask: np.ndarray) -> None:
        self.confusion.add_masks(truth, ra_mask, rd_mask)
        inconsistent, present = consistency_counts(ra_mask, rd_mask, self.num_classes)
        self.inconsistent += inconsistent
        self.present += present
        inconsistent, present = consistency_counts(ra_mask > 0, rd_mask > 0, 2)
        self.occupancy_inconsistent += inconsistent
        self.occupancy_present += present


# --------------------------------------------------------------------------- the job
def compare(cfg: CompareConfig) -> dict[str, Any]:
    """Score every model of ``cfg`` on the same frames; writes compare.json, compare.md and compare_frames.png."""
    from pipelines.figures import plot_compare_frames

    started = time.perf_counter()
    info = StoreInfo.read(cfg.store)
    profile, preset, class_names = info.profile, info.profile.name, info.class_names
    num_classes = len(class_names)
    predictors = [build_predictor(spec, preset, class_names, cfg) for spec in cfg.models]
    window = max(p.n_frames for p in predictors)
    split_name = cfg.split or "all"
    targets = split_windows(cfg.store, cfg.split, window)[:, -1]
    usable = len(targets)
    if cfg.max_frames:
        targets = targets[spread(len(targets), cfg.max_frames)]
    if len(targets) == 0:
        raise UserError(f"split {split_name!r} of {cfg.store} has no frame with {window - 1} earlier frames of its "
                         f"sequence (the window of the longest-window model): nothing to score")
    for predictor in predictors:
        predictor.bind(cfg.store, cfg.split, targets)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)

    picture_slots = [int(targets[i]) for i in spread(len(targets), cfg.pictures)]
    tallies = {p.spec.name: _Tally(num_classes) for p in predictors}
    truth_tally = _Tally(num_classes)
    pictures = _score_frames(cfg, predictors, targets, tallies, truth_tally, picture_slots)

    figure = None
    if pictures:
        figure = plot_compare_frames(
            [(f"{split_name} frame {slot}", pictures[slot]["log_power"],
              {name: masks for name, masks in pictures[slot].items() if name != "log_power"})
             for slot in picture_slots], profile, out / "compare_frames.png",
            title=f"{preset} / {split_name}: the same frames, ground truth first")

    rows = [_model_row(cfg, predictor, tallies[predictor.spec.name], class_names, len(targets))
            for predictor in predictors]
    result: dict[str, Any] = {
        "store": str(cfg.store), "out": str(cfg.out), "split": split_name, "preset": preset,
        "classes": list(class_names), "frames": len(targets), "frames_usable": usable, "window": window,
        "frames_rule": _frames_rule(split_name, window, len(targets), usable),
        "truth_consistency": consistency(truth_tally.inconsistent, truth_tally.present),
        "truth_occupancy_consistency": consistency(truth_tally.occupancy_inconsistent, truth_tally.occupancy_present),
        "models": rows, "threads": torch.get_num_threads(), "device": cfg.device, "command": cfg.command,
        "macs_conventions": {"macs": "correct (FlopCounterMode FLOPs / 2)",
                             "macs_paper": "transposed convs counted per output position (the paper's counter)"},
        "picture": figure.name if figure else None, "picture_frames": picture_slots,
        "seconds": time.perf_counter() - started,
    }
    (out / "compare.json").write_text(json.dumps(result, indent=2))
    (out / "compare.md").write_text(render_compare(result))
    return result


def _score_frames(cfg: CompareConfig, predictors: list, targets: np.ndarray, tallies: dict[str, _Tally],
                  truth_tally: _Tally, picture_slots: list[int]) -> dict[int, dict[str, Any]]:
    """Every model on every target frame, summed into its tally; the masks of the picture frames."""
    root = open_store(cfg.store)
    arrays = {name: root[name] for name in ("input", "ra_mask", "rd_mask")}
    pictures: dict[int, dict[str, Any]] = {}
    for slot in progress(targets.tolist(), desc=f"compare {cfg.split or 'all'}", unit="frame",
                         disable=not cfg.progress):
        log_power = arrays["input"][slot].astype(np.float32)  # (R, A, D) dB
        truth = {"ra": arrays["ra_mask"][slot], "rd": arrays["rd_mask"][slot]}
        truth_tally.add(truth, truth["ra"], truth["rd"])
        keep = slot in picture_slots
        if keep:
            pictures[slot] = {"log_power": log_power, "ground truth": (truth["ra"], truth["rd"])}
        for predictor in predictors:
            prediction = predictor(slot, log_power)
            tally = tallies[predictor.spec.name]
            tally.add(truth, prediction.ra_mask, prediction.rd_mask)
            tally.seconds.append(prediction.seconds)
            tally.macs.append(prediction.macs)
            tally.macs_paper.append(prediction.macs_paper)
            if keep:
                pictures[slot][predictor.spec.name] = (prediction.ra_mask, prediction.rd_mask)
    return pictures


def _model_row(cfg: CompareConfig, predictor: EraseNetPredictor | BaselinePredictor, tally: _Tally,
               class_names: Sequence[str], frames_scored: int) -> dict[str, Any]:
    """One model's entry of compare.json."""
    return {
        "name": predictor.spec.name, "kind": str(predictor.spec.kind),
        "checkpoints": list(predictor.spec.checkpoints),
        "n_frames": predictor.n_frames, "frames_scored": frames_scored,
        "frames_usable_alone": scored_frames(cfg.store, cfg.split, predictor.n_frames),
        **{view: view_summary(tally.confusion.matrices[view.lower()], class_names) for view in VIEWS},
        "params": int(predictor.params),
        "macs": float(np.mean(tally.macs)), "macs_paper": float(np.mean(tally.macs_paper)),
        "macs_note": predictor.macs_note,
        "consistency": consistency(tally.inconsistent, tally.present),
        "inconsistent": tally.inconsistent, "present": tally.present,
        "occupancy_consistency": consistency(tally.occupancy_inconsistent, tally.occupancy_present),
        "seconds_per_frame": float(np.mean(tally.seconds)), "seconds_median": float(np.median(tally.seconds)),
    }


def _frames_rule(split: str, window: int, scored: int, usable: int) -> str:
    """Why these frames: the longest window, and the --max-frames subset."""
    if window == 1:
        rule = f"every valid frame of split {split!r} (every model reads one frame)"
    else:
        rule = (f"the frames of split {split!r} with their {window - 1} earlier frames of the same sequence in the "
                f"store: the longest model window is {window} frames, so the first {window - 1} frames of every "
                "sequence are scored by no model")
    return rule + (f"; {scored} of these {usable}, evenly spread (--max-frames)" if scored < usable else "")


def render_compare(result: dict[str, Any]) -> str:
    """The markdown report of :func:`compare` (the paper's table form, then how it was measured)."""
    classes = result["classes"]
    header = ["model", *[f"{view} {c}" for view in VIEWS for c in [*classes, "mIoU"]], "params (M)",
              "GMACs [paper]", "RA/RD consistency % [occupancy]", "s / frame", "frames"]
    rows = [[row["name"], *[fmt_pct(value) for view in VIEWS
                            for value in [*(row[view]["iou"][c] for c in classes), row[view]["mIoU"]]],
             f"{row['params'] / 1e6:.3f}", f"{row['macs'] / 1e9:.4f} [{row['macs_paper'] / 1e9:.4f}]",
             f"{fmt_pct(row['consistency'])} [{fmt_pct(row['occupancy_consistency'])}]",
             fmt_num(row["seconds_per_frame"], ".4f"), str(row["frames_scored"])]
            for row in result["models"]]
    lines = [f"# ERASE-Net and the 2-D baselines: {result['preset']} / {result['split']}", "",
             f"Store `{result['store']}`, split `{result['split']}`, **{result['frames']} frames, the same for every "
             f"model**: {result['frames_rule']}.", "",
             "IoU per class and mIoU in % (one confusion matrix per view over the frames, background included); "
             "MACs per frame, correct count (FlopCounterMode / 2) with the paper's counter in brackets (it counts a "
             "transposed conv per output position); consistency: share of the (frame, range bin, class) triples "
             "predicted in either view that both RA and RD predict (in brackets: of the (frame, range bin) pairs "
             "with an object in either view, all classes merged; 100 % for any projection of one RAD labelling; "
             "`pipelines/evaluation/compare.py` `consistency_counts`); seconds per frame: wall clock on this CPU in "
             f"this run, {result['threads']} torch thread(s), from the frame in memory (store reads excluded).", ""]
    lines += md_table(header, rows)
    lines += ["", f"Ground truth RA/RD consistency on these frames: {fmt_pct(result['truth_consistency'])} % "
              f"[{fmt_pct(result['truth_occupancy_consistency'])} %] (the ground-truth masks are projections of one "
              "labelling, like ERASE-Net's: per class, the majority vote of a projection can drop a class that "
              "shares a range bin with another).", "",
              "## Frames and cost per model", ""]
    lines += md_table(["model", "kind", "window (frames)", "frames scored", "frames it could use alone", "MACs",
                     "checkpoints"],
                    [[row["name"], row["kind"], str(row["n_frames"]), str(row["frames_scored"]),
                      str(row["frames_usable_alone"]), row["macs_note"],
                      ", ".join(f"`{path}`" for path in row["checkpoints"])]
                     for row in result["models"]])
    lines += ["", "Every model is scored on the same frames, those the longest-window model can use, so the columns "
              "are comparable; \"frames it could use alone\" says how many each could score on its own.", "",
              "Paper, CARRADA (docs/design.md section 12; other data, for context only): "
              + "; ".join(f"{name} RD {rd} / RA {ra} mIoU, {macs} GMACs" for name, (rd, ra, macs)
                          in PAPER_CARRADA.items()) + ".", "",
              "## Command", "", "```", result["command"] or "(called from Python)", "```", ""]
    if result["picture"]:
        lines += ["## Pictures", "", f"Frames {', '.join(map(str, result['picture_frames']))}:", "",
                  f"![{result['picture']}]({result['picture']})", ""]
    return "\n".join(lines)


def main(cfg: CompareConfig) -> dict[str, Any]:
    """Run the job with ``cfg.threads`` torch threads; returns :func:`compare`'s result."""
    torch.set_num_threads(cfg.threads)
    return compare(cfg)


def format_result(result: dict[str, Any]) -> str:
    return f"{format_summary(result)}\nreport: {result['out']}/compare.md"


def format_summary(result: dict[str, Any]) -> str:
    """One line per model: RD and RA mIoU, GMACs, consistency, seconds per frame."""
    lines = [f"{result['split']}: {result['frames']} frames of {result['store']} (the same for every model)"]
    for row in result["models"]:
        lines.append(f"  {row['name']:<28} RD {fmt_pct(row['RD']['mIoU']):>6}  "
                     f"RA {fmt_pct(row['RA']['mIoU']):>6} mIoU  "
                     f"{row['macs'] / 1e9:8.3f} GMACs  consistency {fmt_pct(row['consistency'])} % "
                     f"[{fmt_pct(row['occupancy_consistency'])} %]  "
                     f"{row['seconds_per_frame']:.3f} s/frame")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(run_module("pipelines.evaluation.compare"))
