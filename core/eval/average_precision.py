"""Average precision of scored detections over a whole dataset, at any IoU threshold.

Matching (per frame, per IoU threshold): detections are taken highest score first (ties keep their
input order); each one matches the not-yet-matched ground-truth box with the highest IoU if that
IoU ≥ threshold, and is then a true positive; otherwise it is a false positive (so a duplicate
detection of an already-matched box is a false positive). Each ground-truth box matches at most once.
This is COCO's rule (pycocotools skips ground truth already matched); VOC's devkit instead takes the box of
highest IoU overall and counts the detection false when that box is taken, which differs only where a
detection overlaps two ground-truth boxes by the threshold.

Accumulation: the true/false-positive flags of all frames are pooled and sorted by score; the
precision–recall curve has one point per distinct score (tied scores enter together, so the curve
does not depend on the order of tied detections across frames). Recall is over every ground-truth
box of the dataset, including those no detection came near.

AP summaries of a curve:
- all-point interpolated (VOC 2010+): area under the precision envelope p̂(r) = max_{r' ≥ r} p(r').
- KITTI R40: mean of p̂ at the 40 recall points 1/40, 2/40, ..., 1 (0 where the curve stops short).
A dataset with no ground-truth box has no recall: its AP is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from core.errors import ShapeError

IouFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def greedy_match(iou: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """True-positive flag per detection of one frame.

    iou: D×G IoU between detections and ground-truth boxes; scores: D.
    Returns D bool (in the input order of detections).
    """
    iou = np.asarray(iou, dtype=np.float64)
    scores = np.asarray(scores, dtype=np.float64)
    D = len(scores)
    if iou.shape[0] != D or iou.ndim != 2:
        raise ShapeError(f"iou: expected shape {D}×G for {D} detections, got {'×'.join(map(str, iou.shape))}")
    tp = np.zeros(D, dtype=bool)
    if D == 0 or iou.shape[1] == 0:
        return tp
    taken = np.zeros(iou.shape[1], dtype=bool)
    for d in np.argsort(-scores, kind="stable"):
        candidates = np.where(taken, -np.inf, iou[d])
        g = int(np.argmax(candidates))
        if candidates[g] >= iou_threshold:
            taken[g] = True
            tp[d] = True
    return tp


def precision_recall(scores: np.ndarray, tp: np.ndarray, num_gt: int):
    """PR curve of pooled detections: scores D, tp D bool, num_gt ground-truth boxes in all.

    Returns (precision P, recall P, thresholds P) with one point per distinct score, in decreasing
    score order: point i counts every detection with score ≥ thresholds[i].
    """
    scores = np.asarray(scores, dtype=np.float64)
    tp = np.asarray(tp, dtype=bool)
    if scores.shape != tp.shape:
        raise ShapeError(f"scores and tp must have the same shape, got {scores.shape} and {tp.shape}")
    order = np.argsort(-scores, kind="stable")
    s, t = scores[order], tp[order]
    ctp = np.cumsum(t)
    cfp = np.cumsum(~t)
    # Last index of each run of equal scores: the curve is only defined between distinct scores.
    last = np.nonzero(np.append(s[1:] != s[:-1], True))[0] if len(s) else np.zeros(0, dtype=int)
    ctp, cfp = ctp[last].astype(np.float64), cfp[last].astype(np.float64)
    precision = ctp / np.maximum(ctp + cfp, 1.0)
    recall = ctp / num_gt if num_gt > 0 else np.full(len(last), np.nan)
    return precision, recall, s[last]


def precision_envelope(precision: np.ndarray) -> np.ndarray:
    """p̂[i] = max_{j ≥ i} precision[j] (recall is non-decreasing along the curve)."""
    return np.maximum.accumulate(np.asarray(precision, dtype=np.float64)[::-1])[::-1]


def ap_all_point(precision: np.ndarray, recall: np.ndarray) -> float:
    """All-point interpolated AP (VOC 2010+): Σ over recall steps of Δrecall × p̂."""
    precision, recall = np.asarray(precision, np.float64), np.asarray(recall, np.float64)
    if np.isnan(recall).any():
        return float("nan")
    if len(recall) == 0:
        return 0.0
    env = precision_envelope(precision)
    d_recall = np.diff(np.concatenate([[0.0], recall]))
    return float(np.sum(d_recall * env))


def ap_r40(precision: np.ndarray, recall: np.ndarray) -> float:
    """KITTI R40 AP: mean over r ∈ {1/40, ..., 40/40} of max precision at recall ≥ r (0 if none)."""
    precision, recall = np.asarray(precision, np.float64), np.asarray(recall, np.float64)
    if np.isnan(recall).any():
        return float("nan")
    levels = np.arange(1, 41) / 40.0
    if len(recall) == 0:
        return 0.0
    env = precision_envelope(precision)
    # First curve point reaching each recall level (recall is non-decreasing); the envelope there
    # is the best precision at any recall ≥ the level. The tolerance absorbs k/40 rounding.
    first = np.searchsorted(recall, levels - 1e-12, side="left")
    reached = first < len(recall)
    vals = np.zeros(len(levels))
    vals[reached] = env[first[reached]]
    return float(np.mean(vals))


@dataclass
class _Pool:
    scores: list = field(default_factory=list)
    tp: dict = field(default_factory=dict)  # threshold -> list of D bool arrays
    num_gt: int = 0


class APAccumulator:
    """Pools detections of many frames for one class and one IoU function; AP at each threshold.

    Usage: `acc = APAccumulator(iou_fn=iou_3d, thresholds=(0.33, 0.5, 0.75))`, then
    `acc.add_frame(pred_boxes, pred_scores, gt_boxes)` per frame, then `acc.ap(0.5)`,
    `acc.ap(0.5, method="r40")` or `acc.curve(0.5)`.
    """

    def __init__(self, *, iou_fn: IouFn, thresholds):
        self.iou_fn = iou_fn
        self.thresholds = tuple(float(t) for t in thresholds)
        self._pool = _Pool(tp={t: [] for t in self.thresholds})

    @property
    def num_gt(self) -> int:
        return self._pool.num_gt

    @property
    def num_detections(self) -> int:
        return int(sum(len(s) for s in self._pool.scores))

    def add_frame(self, pred_boxes, pred_scores, gt_boxes) -> None:
        """One frame: pred_boxes D×7, pred_scores D, gt_boxes G×7 (same frame as the preds)."""
        scores = np.asarray(pred_scores, dtype=np.float64).reshape(-1)  # D
        gt = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 7)      # G×7
        pred = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 7)  # D×7
        if len(pred) != len(scores):
            raise ShapeError(f"{len(pred)} predicted boxes but {len(scores)} scores")
        iou = self.iou_fn(pred, gt) if len(pred) and len(gt) else np.zeros((len(pred), len(gt)))
        self._pool.scores.append(scores)
        self._pool.num_gt += len(gt)
        for t in self.thresholds:
            self._pool.tp[t].append(greedy_match(iou, scores, t))

    def curve(self, threshold: float):
        """(precision, recall, score thresholds) of the pooled detections at `threshold`."""
        t = float(threshold)
        if t not in self._pool.tp:
            raise KeyError(f"IoU threshold {t} was not accumulated (have {self.thresholds})")
        scores = np.concatenate(self._pool.scores) if self._pool.scores else np.zeros(0)
        tp = np.concatenate(self._pool.tp[t]) if self._pool.tp[t] else np.zeros(0, dtype=bool)
        return precision_recall(scores, tp, self._pool.num_gt)

    def ap(self, threshold: float, method: str = "all_point") -> float:
        """AP at `threshold`: method "all_point" (VOC) or "r40" (KITTI). NaN without ground truth."""
        precision, recall, _ = self.curve(threshold)
        if self._pool.num_gt == 0:
            return float("nan")
        if method == "all_point":
            return ap_all_point(precision, recall)
        if method == "r40":
            return ap_r40(precision, recall)
        raise ValueError(f"unknown AP method {method!r}; use 'all_point' or 'r40'")
