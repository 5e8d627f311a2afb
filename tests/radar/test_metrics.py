"""radar.metrics against hand-computed cases: the distance rule, greedy matching, AP, IoU."""

import numpy as np
import pytest

from radar.metrics import (
    DetectionEvaluator,
    average_precision,
    confusion_matrix,
    iou_per_class,
    match_frame,
    mean_iou,
)


def _match(pred_xy, pred_dop, scores, truth_xy, truth_dop, k):
    return match_frame(np.array(pred_xy, float), np.array(pred_dop, float), np.array(scores, float),
                       np.array(truth_xy, float), np.array(truth_dop, float), k).tolist()


def test_distance_rule_in_metres_and_doppler_bins():
    truth = [[0.0, 10.0]]
    # 0.9 m away and 0.5 bins off: a match at k = 1
    assert _match([[0.9, 10.0]], [5.5], [1.0], truth, [5.0], 1.0) == [True]
    # 1.1 m away: not at k = 1, but at k = 3
    assert _match([[0.0, 11.1]], [5.0], [1.0], truth, [5.0], 1.0) == [False]
    assert _match([[0.0, 11.1]], [5.0], [1.0], truth, [5.0], 3.0) == [True]
    # exactly k metres is in, exactly k Doppler bins is out ("differs by less than k bins")
    assert _match([[0.0, 11.0]], [5.0], [1.0], truth, [5.0], 1.0) == [True]
    assert _match([[0.0, 10.0]], [6.0], [1.0], truth, [5.0], 1.0) == [False]
    assert _match([[0.0, 10.0]], [5.99], [1.0], truth, [5.0], 1.0) == [True]
    # close in metres, far in Doppler: no match even at k = 5
    assert _match([[0.0, 10.0]], [12.0], [1.0], truth, [5.0], 5.0) == [False]


def test_duplicates_and_greedy_order():
    truth_xy, truth_dop = [[0.0, 10.0], [3.0, 10.0]], [5.0, 5.0]
    # two predictions on the first object: the higher score matches, the other is a duplicate (FP)
    # although the second object lies 2.5 m away (within k = 3) it is matched to the nearest free truth first
    tp = _match([[0.2, 10.0], [0.1, 10.0]], [5.0, 5.0], [0.6, 0.9], truth_xy, truth_dop, 1.0)
    assert tp == [False, True]
    # at k = 3 the lower-scored one takes the remaining object (2.8 m away)
    tp = _match([[0.2, 10.0], [0.1, 10.0]], [5.0, 5.0], [0.6, 0.9], truth_xy, truth_dop, 3.0)
    assert tp == [True, True]
    # empty inputs
    assert _match(np.zeros((0, 2)), [], [], truth_xy, truth_dop, 1.0) == []
    assert _match([[0.0, 10.0]], [5.0], [1.0], np.zeros((0, 2)), [], 1.0) == [False]


def test_ap_hand_computed():
    # ranked: TP, FP, TP against 3 objects -> precision 1, 1/2, 2/3 at recall 1/3, 1/3, 2/3.
    # Monotone envelope: 1 up to recall 1/3 (points 0.00..0.33: 34), 2/3 up to 2/3 (0.34..0.66: 33), 0 after.
    result = average_precision(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), 3)
    assert result.ap == pytest.approx((34 * 1.0 + 33 * 2 / 3) / 101)
    np.testing.assert_allclose(result.precision, [1.0, 0.5, 2 / 3])
    np.testing.assert_allclose(result.recall, [1 / 3, 1 / 3, 2 / 3])
    # input order does not matter, scores do
    shuffled = average_precision(np.array([0.7, 0.9, 0.8]), np.array([True, True, False]), 3)
    assert shuffled.ap == pytest.approx(result.ap)


def test_ap_edges_and_ties():
    assert average_precision(np.array([0.5, 0.4]), np.array([True, True]), 2).ap == pytest.approx(1.0)
    assert average_precision(np.zeros(0), np.zeros(0, bool), 4).ap == 0.0
    assert np.isnan(average_precision(np.array([0.3]), np.array([False]), 0).ap)
    # ties keep the order in which predictions were added (a stable sort): FP first costs precision
    tp_first = average_precision(np.array([0.5, 0.5]), np.array([True, False]), 1).ap
    fp_first = average_precision(np.array([0.5, 0.5]), np.array([False, True]), 1).ap
    assert tp_first == pytest.approx(1.0)
    assert fp_first == pytest.approx(0.5)


def test_detection_evaluator_over_frames():
    evaluator = DetectionEvaluator()
    # frame 1: one object, found within 0.5 m; frame 2: one object missed, one false positive far away
    evaluator.add([[0.0, 10.5]], [4.0], [0.9], [[0.0, 10.0]], [4.0])
    evaluator.add([[20.0, 20.0]], [4.0], [0.8], [[-5.0, 10.0]], [4.0])
    summary = evaluator.summary()
    # ranked TP (0.9), FP (0.8); 2 objects -> precision 1 up to recall 0.5: points 0..50 -> 51 / 101
    for k in ("AP@1", "AP@3", "AP@5"):
        assert summary[k] == pytest.approx(51 / 101)
    assert summary["mAP"] == pytest.approx(51 / 101)
    assert evaluator.n_truth == 2 and evaluator.n_frames == 2


def test_confusion_and_iou_hand_computed():
    truth = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1])
    pred = np.array([0, 0, 0, 0, 0, 1, 0, 0, 1, 1, 1])
    confusion = confusion_matrix(truth, pred, 2)
    np.testing.assert_array_equal(confusion, [[5, 1], [2, 3]])
    np.testing.assert_allclose(iou_per_class(confusion), [5 / 8, 3 / 6])
    assert mean_iou(confusion) == pytest.approx((5 / 8 + 1 / 2) / 2)


def test_iou_absent_class_and_bad_labels():
    confusion = np.array([[4, 0, 0], [0, 2, 0], [0, 0, 0]])  # class 2 in neither truth nor prediction
    iou = iou_per_class(confusion)
    assert iou[:2].tolist() == [1.0, 1.0] and np.isnan(iou[2])
    assert mean_iou(confusion) == 1.0
    # a class predicted but never true has IoU 0 and counts in the mean
    assert mean_iou(np.array([[3, 1], [0, 0]])) == pytest.approx((3 / 4 + 0) / 2)
    with pytest.raises(ValueError, match="labels must lie in"):
        confusion_matrix(np.array([0, 3]), np.array([0, 1]), 3)
    with pytest.raises(ValueError, match="differ in shape"):
        confusion_matrix(np.zeros(3, int), np.zeros(4, int), 2)
