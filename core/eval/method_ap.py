"""AP accumulators of one method over several IoU kinds and thresholds (detection, moving objects).

Boxes are canonical (x, y, z, lx, ly, lz, yaw) rows, predictions and ground truth of a frame in the
same frame (docs/conventions.md#boxes).
"""

from __future__ import annotations

from core.eval.average_precision import APAccumulator
from core.eval.iou3d import iou_3d, iou_bev
from core.eval.thresholds import none_if_nan, threshold_key

IOU_FNS = {"3d": iou_3d, "bev": iou_bev}


class MethodAP:
    """AP accumulators of one method: one per IoU kind ("3d", "bev") over the same thresholds."""

    def __init__(self, thresholds, kinds=("3d", "bev")):
        self.thresholds = tuple(float(t) for t in thresholds)
        self.acc = {k: APAccumulator(iou_fn=IOU_FNS[k], thresholds=self.thresholds) for k in kinds}

    def add_frame(self, pred_boxes, pred_scores, gt_boxes) -> None:
        """pred_boxes D×7, pred_scores D, gt_boxes G×7 (one frame, all in the same frame)."""
        for a in self.acc.values():
            a.add_frame(pred_boxes, pred_scores, gt_boxes)

    def summary(self) -> dict:
        """{"ap3d": {"0.5": AP, ...}, "apbev": {...}, "num_gt", "num_pred"} (AP None without ground truth)."""
        out = {}
        for kind, a in self.acc.items():
            out[f"ap{kind}"] = {threshold_key(t): none_if_nan(a.ap(t)) for t in self.thresholds}
        first = next(iter(self.acc.values()))
        out["num_gt"], out["num_pred"] = first.num_gt, first.num_detections
        return out

    def curve(self, threshold: float, kind: str = "3d"):
        """(precision, recall) at one threshold."""
        precision, recall, _ = self.acc[kind].curve(threshold)
        return precision, recall
