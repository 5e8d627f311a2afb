"""The paper's metrics (docs/design.md section 10), pure numpy.

Detection: a predicted centre matches a ground-truth centre when their Cartesian distance is at most
``k`` metres *and* their mean Doppler bins differ by less than ``k`` bins. Within a frame, predictions
are matched greedily by descending score, each to the nearest (in metres) still unmatched ground truth
that passes the rule; each ground truth is matched once, so a second prediction on the same object
(a duplicate) is a false positive. Over a split, all predictions are ranked by score (ties keep the
order they were added in: a stable sort) and AP is the area under the precision-recall curve with
COCO's interpolation: precision made monotone (the maximum precision at any recall >= r), sampled at
the 101 recall points 0, 0.01, ..., 1 (0 where that recall is never reached), averaged.
The paper reports AP at k = 1, 3 and 5 and their mean, mAP. A radar that sees less than the 50 m road radars
those metres were set for gets them scaled (:func:`distance_thresholds_m`: 0.125, 0.375 and 0.625 m on a radar
of 6.25 m), while the Doppler test stays at k bins; the keys keep the paper's names (``AP@1`` is the first level)
and :meth:`DetectionEvaluator.thresholds_note` states the metres.

Segmentation: one confusion matrix per view accumulated over every test frame (rows: truth, columns:
prediction); IoU per class ``TP / (TP + FP + FN)``; mIoU the plain mean over all classes, background
included (the paper's tables do this). A class absent from both truth and prediction has no IoU (NaN)
and is left out of the mean.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from radar.profiles import RadarProfile
from radar.profiles.scene_settings import radar_scale

DISTANCE_THRESHOLDS_M = (1.0, 3.0, 5.0)
COCO_RECALL_POINTS = np.linspace(0.0, 1.0, 101)


def distance_thresholds_m(profile: RadarProfile) -> tuple[float, ...]:
    """The paper's 1/3/5 m scaled to ``profile`` (:func:`radar.profiles.scene_settings.radar_scale`): unchanged
    for every built-in preset, 0.125/0.375/0.625 m for a radar of 6.25 m."""
    scale = radar_scale(profile)
    return tuple(k * scale for k in DISTANCE_THRESHOLDS_M)


# --------------------------------------------------------------------------- detection
def match_frame(pred_xy: np.ndarray, pred_doppler: np.ndarray, pred_score: np.ndarray, truth_xy: np.ndarray,
                truth_doppler: np.ndarray, k: float, doppler_k: float | None = None) -> np.ndarray:
    """True positives of one frame's predictions at threshold ``k`` (``doppler_k`` bins for Doppler, default ``k``).

    Args:
        pred_xy: (N, 2) predicted centres, Cartesian (x, y) in metres.
        pred_doppler: (N,) predicted mean Doppler bins.
        pred_score: (N,) confidences (higher first).
        truth_xy: (M, 2) ground-truth centres in metres; truth_doppler: (M,) Doppler bins.
        k: distance threshold, metres for the position and bins for Doppler.

    Returns:
        (N,) bool, in the order of the inputs: True where the prediction matched a ground truth.
    """
    pred_xy = np.asarray(pred_xy, np.float64).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, np.float64).reshape(-1, 2)
    pred_doppler = np.asarray(pred_doppler, np.float64).reshape(-1)
    truth_doppler = np.asarray(truth_doppler, np.float64).reshape(-1)
    pred_score = np.asarray(pred_score, np.float64).reshape(-1)
    if not (len(pred_xy) == len(pred_doppler) == len(pred_score)):
        raise ValueError(f"predictions disagree in length: xy {len(pred_xy)}, doppler {len(pred_doppler)}, "
                         f"score {len(pred_score)}")
    if len(truth_xy) != len(truth_doppler):
        raise ValueError(f"ground truth disagrees in length: xy {len(truth_xy)}, doppler {len(truth_doppler)}")
    return _greedy_match(pred_xy, pred_doppler, pred_score, truth_xy, truth_doppler, k, doppler_k)[0]


def matched_truths(pred_xy: np.ndarray, pred_doppler: np.ndarray, pred_score: np.ndarray, truth_xy: np.ndarray,
                   truth_doppler: np.ndarray, k: float, doppler_k: float | None = None) -> np.ndarray:
    """(M,) bool: which ground truths :func:`match_frame`'s predictions matched (the same one-to-one rule)."""
    return _greedy_match(*(np.asarray(a, np.float64) for a in (pred_xy, pred_doppler, pred_score)),
                         np.asarray(truth_xy, np.float64).reshape(-1, 2),
                         np.asarray(truth_doppler, np.float64).reshape(-1), k, doppler_k)[1]


def _greedy_match(pred_xy: np.ndarray, pred_doppler: np.ndarray, pred_score: np.ndarray, truth_xy: np.ndarray,
                  truth_doppler: np.ndarray, k: float,
                  doppler_k: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Predictions by descending score each take the nearest untaken eligible truth: (N,) matched predictions,
    (M,) matched truths."""
    pred_xy = pred_xy.reshape(-1, 2)
    tp, taken = np.zeros(len(pred_xy), bool), np.zeros(len(truth_xy), bool)
    if len(pred_xy) == 0 or len(truth_xy) == 0:
        return tp, taken
    distance = np.linalg.norm(pred_xy[:, None, :] - truth_xy[None, :, :], axis=2)  # (N, M) metres
    doppler_k = k if doppler_k is None else doppler_k
    eligible = (distance <= k) & (np.abs(pred_doppler.reshape(-1)[:, None] - truth_doppler[None, :]) < doppler_k)
    for i in np.argsort(-pred_score.reshape(-1), kind="stable"):
        candidates = np.flatnonzero(eligible[i] & ~taken)
        if len(candidates):
            j = candidates[np.argmin(distance[i, candidates])]
            taken[j] = True
            tp[i] = True
    return tp, taken


@dataclass(frozen=True)
class PrecisionRecall:
    """AP and its curve. ``precision``/``recall``/``score``: (N,) after each ranked prediction."""

    ap: float
    precision: np.ndarray
    recall: np.ndarray
    score: np.ndarray
    n_truth: int


def average_precision(scores: np.ndarray, tp: np.ndarray, n_truth: int) -> PrecisionRecall:
    """COCO-interpolated AP (101 recall points) of predictions with ``scores`` (N,) and ``tp`` (N,) bool
    against ``n_truth`` ground-truth objects. With no ground truth AP is NaN (undefined)."""
    scores = np.asarray(scores, np.float64).reshape(-1)
    tp = np.asarray(tp, bool).reshape(-1)
    if len(scores) != len(tp):
        raise ValueError(f"scores ({len(scores)}) and tp ({len(tp)}) differ in length")
    if n_truth < 0:
        raise ValueError(f"n_truth must be >= 0, got {n_truth}")
    order = np.argsort(-scores, kind="stable")
    tp_cum = np.cumsum(tp[order])
    fp_cum = np.cumsum(~tp[order])
    precision = tp_cum / np.maximum(tp_cum + fp_cum, 1)
    recall = tp_cum / n_truth if n_truth else np.zeros(len(order))
    if n_truth == 0:
        return PrecisionRecall(float("nan"), precision, recall, scores[order], 0)
    sampled = np.zeros_like(COCO_RECALL_POINTS)
    if len(precision):
        envelope = np.maximum.accumulate(precision[::-1])[::-1]  # best precision at any recall >= r
        idx = np.searchsorted(recall, COCO_RECALL_POINTS, side="left")
        reached = idx < len(envelope)
        sampled[reached] = envelope[idx[reached]]
    return PrecisionRecall(float(np.mean(sampled)), precision, recall, scores[order], n_truth)


@dataclass
class DetectionEvaluator:
    """Accumulates frames, then gives AP per distance threshold and mAP (their mean).

    ``levels`` (default: the thresholds) are the Doppler thresholds in bins and name the keys; a radar's scaled
    evaluator comes from :meth:`for_profile`.
    """

    thresholds: Sequence[float] = DISTANCE_THRESHOLDS_M
    levels: Sequence[float] | None = None
    _scores: list[np.ndarray] = field(default_factory=list)
    _tp: dict[float, list[np.ndarray]] = field(default_factory=dict)
    n_truth: int = 0
    n_frames: int = 0

    def add(self, pred_xy: np.ndarray, pred_doppler: np.ndarray, pred_score: np.ndarray, truth_xy: np.ndarray,
            truth_doppler: np.ndarray) -> None:
        """One frame (shapes as in :func:`match_frame`)."""
        self._scores.append(np.asarray(pred_score, np.float64).reshape(-1))
        for k, level in zip(self.thresholds, self._levels, strict=True):
            self._tp.setdefault(k, []).append(
                match_frame(pred_xy, pred_doppler, pred_score, truth_xy, truth_doppler, k, level))
        self.n_truth += len(np.asarray(truth_doppler).reshape(-1))
        self.n_frames += 1

    @classmethod
    def for_profile(cls, profile: RadarProfile) -> DetectionEvaluator:
        """The paper's levels at ``profile``'s scale (:func:`distance_thresholds_m`)."""
        return cls(thresholds=distance_thresholds_m(profile), levels=DISTANCE_THRESHOLDS_M)

    @property
    def _levels(self) -> tuple[float, ...]:
        return tuple(self.thresholds if self.levels is None else self.levels)

    def thresholds_note(self) -> str:
        """What the AP keys mean, e.g. ``AP@1/3/5: within 0.125/0.375/0.625 m and 1/3/5 Doppler bins``."""
        levels = "/".join(f"{v:g}" for v in self._levels)
        metres = "/".join(f"{v:.3g}" for v in self.thresholds)
        return f"AP@{levels}: within {metres} m and {levels} Doppler bins"

    def curves(self) -> dict[float, PrecisionRecall]:
        scores = np.concatenate(self._scores) if self._scores else np.zeros(0)
        return {k: average_precision(scores, np.concatenate(self._tp.get(k, [np.zeros(0, bool)])), self.n_truth)
                for k in self.thresholds}

    def summary(self) -> dict[str, float]:
        """``{"AP@1": ..., "AP@3": ..., "AP@5": ..., "mAP": ...}`` (thresholds in metres/bins)."""
        curves = self.curves()
        out = {f"AP@{level:g}": curve.ap for level, curve in zip(self._levels, curves.values(), strict=True)}
        out["mAP"] = float(np.mean([c.ap for c in curves.values()])) if curves else float("nan")
        return out


# --------------------------------------------------------------------------- segmentation
def confusion_matrix(truth: np.ndarray, pred: np.ndarray, num_classes: int) -> np.ndarray:
    """(C, C) int64 counts, rows = ground-truth class, columns = predicted class, of two equal-shape
    integer label arrays with values in ``[0, num_classes)``."""
    truth = np.asarray(truth)
    pred = np.asarray(pred)
    if truth.shape != pred.shape:
        raise ValueError(f"truth {truth.shape} and prediction {pred.shape} differ in shape")
    truth = truth.reshape(-1).astype(np.int64)
    pred = pred.reshape(-1).astype(np.int64)
    for name, arr in (("truth", truth), ("prediction", pred)):
        if arr.size and (arr.min() < 0 or arr.max() >= num_classes):
            raise ValueError(f"{name} labels must lie in [0, {num_classes}), found [{arr.min()}, {arr.max()}]")
    return np.bincount(truth * num_classes + pred, minlength=num_classes**2).reshape(num_classes, num_classes)


def iou_per_class(confusion: np.ndarray) -> np.ndarray:
    """(C,) IoU of each class from a (C, C) confusion matrix; NaN where the class is in neither."""
    confusion = np.asarray(confusion, np.float64)
    tp = np.diag(confusion)
    union = confusion.sum(0) + confusion.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, tp / np.where(union > 0, union, 1), np.nan)


def mean_iou(confusion: np.ndarray) -> float:
    """Plain mean of :func:`iou_per_class` over the classes that occur (background included)."""
    iou = iou_per_class(confusion)
    return float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")


# --------------------------------------------------------------------------- RA/RD consistency
def consistency_counts(ra_mask: np.ndarray, rd_mask: np.ndarray, num_classes: int) -> tuple[int, int]:
    """``(inconsistent, present)`` (range bin, class) pairs of one frame's RA (R, A) and RD (R, D) masks.

    For every range bin r and non-background class c: c is *present in a view* at r when some cell of
    that view's row r has class c. The pair (r, c) counts in ``present`` when c is present in either
    view, and in ``inconsistent`` when it is present in exactly one. Summed over frames,
    consistency = 1 - inconsistent / present (:func:`consistency`): the share of the (frame, range,
    class) triples predicted somewhere on which both views agree.

    *Occupancy* consistency is the same with every object class merged into one,
    ``consistency_counts(ra_mask > 0, rd_mask > 0, 2)``: RA row r holds an object iff RD row r does.

    The RA and RD masks of one RAD labelling (:func:`radar.transforms.project_ra` / ``project_rd``, ERASE-Net's
    and the ground truth's) always have occupancy consistency 1: both rows r are background only where the
    cube's range slice r is. Per class they agree too when each range bin holds at most one object class;
    when two classes share a range bin, the majority vote of a projection can drop one of them in one
    view and keep it in the other (a few voxels of one class inside an object of another, or two objects
    at the same range and Doppler), so class consistency can be below 1 even for ERASE-Net.
    """
    classes = np.arange(1, num_classes)
    ra_has = (np.asarray(ra_mask)[:, :, None] == classes).any(axis=1)  # (R, C - 1)
    rd_has = (np.asarray(rd_mask)[:, :, None] == classes).any(axis=1)
    return int((ra_has ^ rd_has).sum()), int((ra_has | rd_has).sum())


def consistency(inconsistent: int, present: int) -> float:
    """1 - inconsistent / present; NaN when no class was predicted anywhere (nothing to agree on)."""
    return 1.0 - inconsistent / present if present else float("nan")
