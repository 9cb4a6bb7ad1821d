"""AP against hand-computed precision–recall lists, greedy matching, ties and duplicates."""

import numpy as np
import pytest

from core.eval.average_precision import (APAccumulator, ap_all_point, ap_r40, greedy_match,
                                         precision_recall)
from core.eval.iou3d import iou_3d


def slow_all_point_ap(precision, recall):
    """VOC 2010 code, literally: sentinels, envelope from the right, sum where recall changes."""
    mrec = [0.0] + list(recall) + [1.0]
    mpre = [0.0] + list(precision) + [0.0]
    for i in range(len(mpre) - 2, -1, -1):
        mpre[i] = max(mpre[i], mpre[i + 1])
    return sum((mrec[i + 1] - mrec[i]) * mpre[i + 1] for i in range(len(mrec) - 1) if mrec[i + 1] != mrec[i])


def test_hand_computed_pr_list():
    # Ranked TP, FP, TP, FP, TP with 4 ground-truth boxes:
    # precision 1, 1/2, 2/3, 2/4, 3/5; recall 1/4, 1/4, 2/4, 2/4, 3/4.
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
    tp = np.array([True, False, True, False, True])
    p, r, thr = precision_recall(scores, tp, num_gt=4)
    np.testing.assert_allclose(p, [1, 1 / 2, 2 / 3, 2 / 4, 3 / 5])
    np.testing.assert_allclose(r, [1 / 4, 1 / 4, 2 / 4, 2 / 4, 3 / 4])
    np.testing.assert_allclose(thr, scores)
    # Envelope 1, 2/3, 2/3, 3/5, 3/5 → AP = 1/4·1 + 1/4·2/3 + 1/4·3/5.
    expected = 0.25 * 1 + 0.25 * (2 / 3) + 0.25 * (3 / 5)
    assert ap_all_point(p, r) == pytest.approx(expected, abs=1e-12)
    assert ap_all_point(p, r) == pytest.approx(slow_all_point_ap(p, r), abs=1e-12)
    # R40: levels 1..10/40 → 1, 11..20/40 → 2/3, 21..30/40 → 3/5, 31..40/40 → 0.
    assert ap_r40(p, r) == pytest.approx((10 * 1 + 10 * (2 / 3) + 10 * (3 / 5)) / 40, abs=1e-12)


def test_ties_enter_the_curve_together():
    # Two detections tied at 0.8 (one TP, one FP): one curve point for both, whatever their order.
    scores = np.array([0.9, 0.8, 0.8, 0.3])
    p1, r1, _ = precision_recall(scores, np.array([True, True, False, True]), num_gt=3)
    p2, r2, _ = precision_recall(scores, np.array([True, False, True, True]), num_gt=3)
    np.testing.assert_allclose(p1, [1, 2 / 3, 3 / 4])
    np.testing.assert_allclose(r1, [1 / 3, 2 / 3, 1])
    np.testing.assert_allclose(p1, p2)
    np.testing.assert_allclose(r1, r2)
    assert ap_all_point(p1, r1) == pytest.approx(1 / 3 + 1 / 3 * 3 / 4 + 1 / 3 * 3 / 4)


def test_perfect_and_empty():
    p, r, _ = precision_recall(np.array([0.5, 0.4]), np.array([True, True]), num_gt=2)
    assert ap_all_point(p, r) == 1.0 and ap_r40(p, r) == 1.0
    p, r, _ = precision_recall(np.zeros(0), np.zeros(0, bool), num_gt=3)
    assert ap_all_point(p, r) == 0.0 and ap_r40(p, r) == 0.0
    p, r, _ = precision_recall(np.array([0.5]), np.array([False]), num_gt=0)
    assert np.isnan(ap_all_point(p, r))


def test_greedy_match_highest_score_first_each_gt_once():
    # Two detections on GT 0 (the higher-scored wins, the other is a duplicate FP), one on GT 1
    # below threshold, one that would prefer the taken GT 0 but still clears GT 1.
    iou = np.array([[0.9, 0.0],
                    [0.95, 0.0],
                    [0.0, 0.4],
                    [0.8, 0.6]])
    scores = np.array([0.9, 0.5, 0.7, 0.6])
    tp = greedy_match(iou, scores, 0.5)
    np.testing.assert_array_equal(tp, [True, False, False, True])
    np.testing.assert_array_equal(greedy_match(iou, scores, 0.95), [False, True, False, False])
    assert greedy_match(np.zeros((0, 2)), np.zeros(0), 0.5).shape == (0,)
    assert not greedy_match(np.zeros((2, 0)), np.ones(2), 0.5).any()


def test_accumulator_over_frames_counts_duplicates_and_missed_gt():
    gt_a = np.array([[0, 0, 10, 4, 2, 2, 0.0], [5, 0, 10, 4, 2, 2, 0.0]])
    gt_b = np.array([[0, 0, 20, 4, 2, 2, 0.3]])
    acc = APAccumulator(iou_fn=iou_3d, thresholds=(0.5, 0.75))
    # Frame A: exact hit (0.9), duplicate of it (0.8), a box half-shifted along x (IoU 1/3, 0.7).
    shifted = gt_a[1].copy()
    shifted[0] += 2.0
    acc.add_frame(np.stack([gt_a[0], gt_a[0], shifted]), [0.9, 0.8, 0.7], gt_a)
    # Frame B: an exact hit at low score; frame C: no GT, one false alarm.
    acc.add_frame(gt_b, [0.6], gt_b)
    acc.add_frame(gt_b, [0.95], np.zeros((0, 7)))
    assert acc.num_gt == 3 and acc.num_detections == 5
    p, r, _ = acc.curve(0.5)
    # Ranked: 0.95 FP, 0.9 TP, 0.8 FP (duplicate), 0.7 FP (IoU 1/3), 0.6 TP.
    np.testing.assert_allclose(p, [0, 1 / 2, 1 / 3, 1 / 4, 2 / 5])
    np.testing.assert_allclose(r, [0, 1 / 3, 1 / 3, 1 / 3, 2 / 3])
    assert acc.ap(0.5) == pytest.approx(1 / 3 * 1 / 2 + 1 / 3 * 2 / 5)
    assert acc.ap(0.5) == pytest.approx(slow_all_point_ap(p, r))
    assert acc.ap(0.75) == acc.ap(0.5)  # the hits are exact, the miss is at 1/3
    empty = APAccumulator(iou_fn=iou_3d, thresholds=(0.5,))
    empty.add_frame(gt_b, [0.5], np.zeros((0, 7)))
    assert np.isnan(empty.ap(0.5))
    with pytest.raises(KeyError):
        acc.ap(0.33)
