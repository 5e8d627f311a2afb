"""Scoring shared by training validation, ``evaluate``, ``compare`` and ``slim-sweep``: which frames
(:func:`pipelines.datasets.spread.subset`), detection AP over decoded centres (:class:`DetectionScorer`,
:func:`score_detector`),
per-view confusion and mIoU with one key convention (:class:`ViewConfusion`, views ``"ra"`` and
``"rd"``), and the 2-D baselines' scores (:func:`score_baseline`). The metrics themselves are numpy
functions in :mod:`radar.metrics`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from models.detector.targets import CentreTargets, build_centre_targets
from models.erasenet.detection import detect_centres
from pipelines.datasets.spread import subset
from pipelines.datasets.store import CENTRE_COLUMNS, OBJECT_COLUMN, StoreDataset
from pipelines.datasets.views import ViewDataset, collate_views, masks_of, model_inputs
from radar.centres import SCORE_THRESHOLD, Centres
from radar.doppler import DOPPLER_REFINEMENT, DopplerRefinement
from radar.metrics import DetectionEvaluator, confusion_matrix, iou_per_class, matched_truths, mean_iou
from radar.profiles import RadarProfile
from radar.profiles.scene_settings import radar_scale

VIEWS = ("ra", "rd")


def frame_centres(sample: Mapping[str, Any]) -> np.ndarray:
    """(N, 3) float64 (range, angle, Doppler) bins of a store sample's objects (from its object table)."""
    n = int(sample["n_objects"])
    objects = sample["objects"]
    objects = objects.double().numpy() if isinstance(objects, torch.Tensor) else np.asarray(objects, np.float64)
    return objects[:n, CENTRE_COLUMNS]


def centre_targets(samples: Sequence[Mapping[str, Any]], grid_shape: tuple[int, int], *, heatmap_classes: int = 1,
                   centre_weights: Sequence[np.ndarray] | None = None) -> CentreTargets:
    """The detector's training targets for store samples: one heatmap, or one per foreground class."""
    classes = None
    if heatmap_classes > 1:  # class id 0 is background: foreground class c is heatmap channel c - 1
        classes = [np.asarray(s["objects"][:int(s["n_objects"]), OBJECT_COLUMN["class_id"]], np.int64) - 1
                   for s in samples]
    return build_centre_targets([frame_centres(s) for s in samples], grid_shape, centre_weights=centre_weights,
                                heatmap_classes=heatmap_classes, classes=classes)


# --------------------------------------------------------------------------- detection
class DetectionScorer:
    """AP at 1/3/5 m (scaled to a radar that sees less than 50 m) over frames: each frame's decoded centres against
    its object table."""

    RECALL_DISTANCE = 3.0  # metres (and Doppler bins) of the per-class recall at the operating point, at 50 m scale

    def __init__(self, profile: RadarProfile) -> None:
        self.profile = profile
        self.evaluator = DetectionEvaluator.for_profile(profile)
        self.recall_distance_m = self.RECALL_DISTANCE * radar_scale(profile)
        n = len(profile.class_names) + 1
        self.found, self.truths = np.zeros(n, np.int64), np.zeros(n, np.int64)  # per class id (0: background)

    def add(self, centres: Centres, objects: np.ndarray) -> None:
        """``centres``: the frame's scored detections; ``objects``: its (N, 10) object table (true objects)."""
        table = np.asarray(objects, np.float64)
        pred_xy = np.stack(self.profile.xy(centres.range_bin, centres.angle_bin), axis=1)
        truth_xy = table[:, [OBJECT_COLUMN["x"], OBJECT_COLUMN["y"]]]
        truth_doppler = table[:, OBJECT_COLUMN["doppler_bin"]]
        self.evaluator.add(pred_xy, centres.doppler_bin, centres.score, truth_xy, truth_doppler)
        kept = centres.score >= SCORE_THRESHOLD  # the centres EraseNet grows regions from
        matched = matched_truths(pred_xy[kept], centres.doppler_bin[kept], centres.score[kept], truth_xy,
                                 truth_doppler, self.recall_distance_m, self.RECALL_DISTANCE)
        classes = table[:, OBJECT_COLUMN["class_id"]].astype(np.int64)
        np.add.at(self.truths, classes, 1)
        np.add.at(self.found, classes[matched], 1)

    def recall_by_class(self) -> dict[str, float]:
        """``recall_<class>``: the share of each class's true objects matched (3 m) by a centre at the operating
        score threshold (:data:`radar.centres.SCORE_THRESHOLD`); NaN for a class with no object."""
        return {f"recall_{name}": float(self.found[i] / self.truths[i]) if self.truths[i] else float("nan")
                for i, name in enumerate(self.profile.class_names, 1)}

    def summary(self) -> dict[str, float]:
        return self.evaluator.summary()

    def thresholds(self) -> dict[str, object]:
        """The AP thresholds as used: ``distance_thresholds_m`` and a sentence (``thresholds``)."""
        return {"distance_thresholds_m": list(self.evaluator.thresholds),
                "thresholds": self.evaluator.thresholds_note()}

    def curves(self):  # noqa: ANN201 (radar.metrics.PrecisionRecall per k)
        return self.evaluator.curves()

    @property
    def n_truth(self) -> int:
        return self.evaluator.n_truth


@torch.no_grad()
def score_detector(detector: nn.Module, store: str, split: str, profile: RadarProfile,
                   normalisation: Mapping[str, Any], *, max_frames: int = 0, score_threshold: float = 0.05,
                   batch_size: int = 8, device: torch.device | str = "cpu",
                   with_loss: bool = False,
                   doppler_refinement: DopplerRefinement | None = DOPPLER_REFINEMENT,
                   history: int = 0) -> dict[str, float]:
    """Detection AP@1/3/5 and mAP of ``detector`` on ``max_frames`` evenly spread frames of ``split`` (0 = all),
    input normalised with the store's global mean/std in dB exactly as :class:`models.erasenet.model.EraseNet` does;
    with ``with_loss`` also ``loss`` (mean total per frame). The Doppler of each centre is refined from the
    frame's cube (:func:`radar.doppler.refine_doppler`) as EraseNet does, unless ``doppler_refinement`` is None.
    With ``history`` H > 0 the detector also reads each frame's H earlier frames of its sequence (a detector with
    ``history_frames`` H); without, it sees single cubes. The model is left in eval mode."""
    detector.eval()
    dataset = StoreDataset(store, split, fields=("input", "objects"), normalise=False, history=history)
    indices = subset(len(dataset), max_frames)
    scorer, loss_sum = DetectionScorer(profile), 0.0
    for start in range(0, len(indices), batch_size):
        samples = [dataset[i] for i in indices[start:start + batch_size]]
        log_power = torch.stack([s["input"] for s in samples])  # (B, D, R, A) dB
        earlier = ({"history": torch.stack([s["history"] for s in samples]),
                    "history_present": torch.stack([s["history_present"] for s in samples])} if history else {})
        outputs, frames = detect_centres(detector, log_power, mean_db=normalisation["mean"],
                                         std_db=normalisation["std"], score_threshold=score_threshold,
                                         doppler_refinement=doppler_refinement, device=device, **earlier)
        if with_loss:
            targets = centre_targets(samples, (profile.n_range, profile.n_angle),
                                     heatmap_classes=getattr(detector.head, "heatmap_classes", 1))
            loss = detector.compute_loss(outputs, {k: v.to(device) for k, v in targets.items()})["total"]
            loss_sum += float(loss) * len(samples)
        for sample, centres in zip(samples, frames, strict=True):
            scorer.add(centres, sample["objects"][:int(sample["n_objects"])])
    result = {**scorer.summary(), **scorer.recall_by_class()}
    if with_loss:
        result["loss"] = loss_sum / max(len(indices), 1)
    return result


# --------------------------------------------------------------------------- segmentation
def view_summary(confusion: np.ndarray, class_names: Sequence[str]) -> dict[str, Any]:
    """IoU per class (None for a class in neither truth nor prediction), mIoU and the confusion matrix."""
    iou = iou_per_class(confusion)
    return {"iou": {name: (None if np.isnan(v) else float(v)) for name, v in zip(class_names, iou, strict=True)},
            "mIoU": mean_iou(confusion), "confusion": confusion.tolist()}


class ViewConfusion:
    """One (C, C) confusion matrix per view (rows truth), summed over frames; views ``"ra"``/``"rd"``."""

    def __init__(self, num_classes: int, views: Sequence[str] = VIEWS) -> None:
        self.num_classes = num_classes
        self.matrices = {view: np.zeros((num_classes, num_classes), np.int64) for view in views}

    def add(self, view: str, truth: np.ndarray, prediction: np.ndarray) -> None:
        self.matrices[view] += confusion_matrix(np.asarray(truth), np.asarray(prediction), self.num_classes)

    def add_masks(self, truth: Mapping[str, np.ndarray], ra_mask: np.ndarray, rd_mask: np.ndarray) -> None:
        """One frame's predicted RA (R, A) and RD (R, D) masks against ``truth["ra"]``, ``truth["rd"]``."""
        self.add("ra", truth["ra"], ra_mask)
        self.add("rd", truth["rd"], rd_mask)

    def miou(self, view: str) -> float:
        return mean_iou(self.matrices[view])

    def summary(self, class_names: Sequence[str]) -> dict[str, dict[str, Any]]:
        return {view: view_summary(matrix, class_names) for view, matrix in self.matrices.items()}


def predicted_views(model: nn.Module) -> tuple[str, ...]:
    """The views a 2-D baseline predicts: its own for a one-view model (U-Net), ``("rd", "ra")`` otherwise."""
    view = getattr(model, "view", None)
    return (view,) if view is not None else ("rd", "ra")


@torch.no_grad()
def score_baseline(model: nn.Module, dataset: ViewDataset, *, num_classes: int, loss_fn: nn.Module | None = None,
                   batch_size: int = 4, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Segmentation scores of a baseline over every window of ``dataset`` (model put in eval mode).

    Returns ``frames`` (windows scored), per predicted view ``confusion_{view}`` ((C, C) list, rows truth),
    ``iou_{view}`` (per class, NaN for a class in neither truth nor prediction), ``mIoU_{view}``, and
    ``mIoU`` (mean over the predicted views); with ``loss_fn`` also ``loss`` (mean total per window).
    """
    model.eval()
    views = predicted_views(model)
    confusion = ViewConfusion(num_classes, views)
    loss_sum = 0.0
    for start in range(0, len(dataset), batch_size):
        batch = collate_views([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        outputs = model(*model_inputs(model, batch, device))
        masks = masks_of(batch, device)
        if loss_fn is not None:
            loss_sum += float(loss_fn(outputs, masks)["total"]) * len(batch["frame"])
        for view in views:
            confusion.add(view, masks[view].cpu().numpy(), outputs[view].argmax(1).cpu().numpy())
    result: dict[str, Any] = {"frames": len(dataset)}
    for view in views:
        matrix = confusion.matrices[view]
        result[f"confusion_{view}"] = matrix.tolist()
        result[f"iou_{view}"] = iou_per_class(matrix).tolist()
        result[f"mIoU_{view}"] = mean_iou(matrix)
    result["mIoU"] = float(np.mean([result[f"mIoU_{view}"] for view in views])) if len(dataset) else float("nan")
    if loss_fn is not None and len(dataset):
        result["loss"] = loss_sum / len(dataset)
    return result
