"""Non-maximum suppression of yaw-rotated boxes by bird's-eye-view IoU (numpy; no torchvision).

Boxes are canonical (x, y, z, lx, ly, lz, yaw) rows, all in one frame (docs/conventions.md#boxes).
"""

from __future__ import annotations

import numpy as np

from core.eval.iou3d import as_boxes, iou_bev


def nms_bev(boxes, scores, iou_threshold: float) -> np.ndarray:
    """Greedy NMS: keep the best-scored box, drop every box whose BEV IoU with it exceeds
    `iou_threshold`, repeat. boxes N×7, scores N. Returns kept indices (int64), best first."""
    b = as_boxes(boxes)
    s = np.asarray(scores.detach().cpu() if hasattr(scores, "detach") else scores, dtype=np.float64).reshape(-1)
    if len(s) != len(b):
        raise ValueError(f"{len(b)} boxes but {len(s)} scores")
    order = np.argsort(-s, kind="stable")
    iou = iou_bev(b, b)                                          # N×N, all pairs at once
    suppressed = np.zeros(len(b), dtype=bool)
    keep = []
    for i in order:
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return np.array(keep, dtype=np.int64)
