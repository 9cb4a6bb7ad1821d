"""KITTI label files scored against each other: `evaluate_label_dirs(pred_dir, gt_dir)`.

One `<frame>.txt` per frame in each directory (see core.eval.kitti_labels); predictions carry a
score column. A frame with no prediction file has no detections; a prediction file with no
ground-truth file is a frame without objects (all its detections are false positives, and the
result warns). No 2D-size, truncation or occlusion filters: every ground-truth box of a class counts.

Per class, `detection.<class>.ap3d` and `.apbev` map IoU threshold keys ("0.33", "0.5", "0.75", and
any extra given) to all-point AP in [0, 1] (None where the class has no ground-truth box), plus
`ap3d_r40` / `apbev_r40` (KITTI R40), `num_gt` and `num_pred`.
"""

from __future__ import annotations

import os

import numpy as np

from core.errors import DataError
from core.eval.average_precision import APAccumulator
from core.eval.iou3d import iou_3d, iou_bev
from core.eval.kitti_labels import FrameLabels, list_frames, read_label_file
from core.eval.thresholds import iou_thresholds, none_if_nan, threshold_key

IGNORED_TYPES = ("DontCare",)
MATCHING = ("greedy per frame, highest score first; a detection matches the unmatched ground-truth box "
            "of its class with the highest IoU if that IoU >= threshold; each ground-truth box at most once")


def _read_dir(directory: str, *, require_score: bool) -> dict[str, FrameLabels]:
    return {f: read_label_file(os.path.join(directory, f + ".txt"), require_score=require_score)
            for f in list_frames(directory)}


def evaluate_label_dirs(pred_dir: str, gt_dir: str, ious=None, classes=None) -> tuple[dict, dict]:
    """Score the predictions of `pred_dir` against `gt_dir`.

    Returns (metrics, curves): metrics as a report's metrics.json holds them; curves[(class, kind, key)] =
    (precision, recall) for the plots, kind in {"3d", "bev"}.
    """
    thresholds = iou_thresholds(ious)
    gt = _read_dir(gt_dir, require_score=False)
    if not gt:
        raise DataError(f"no ground-truth label files (*.txt) in {gt_dir}")
    pred = _read_dir(pred_dir, require_score=True)
    warnings = []
    extra = sorted(set(pred) - set(gt))
    if extra:
        warnings.append(f"{len(extra)} prediction file(s) have no ground-truth file and count as frames "
                        f"without objects (e.g. {extra[0]}.txt)")
    missing = sorted(set(gt) - set(pred))
    if missing:
        warnings.append(f"{len(missing)} frame(s) have no prediction file and count as no detections "
                        f"(e.g. {missing[0]}.txt)")
    if classes:
        names = list(dict.fromkeys(classes))
    else:
        names = sorted({t for labels in gt.values() for t in labels.types if t not in IGNORED_TYPES})
    empty = FrameLabels(types=[], boxes_cam=np.zeros((0, 7)), scores=np.zeros(0))
    frames = sorted(set(gt) | set(pred))
    per_class, curves = {}, {}
    for name in names:
        acc = {"3d": APAccumulator(iou_fn=iou_3d, thresholds=thresholds),
               "bev": APAccumulator(iou_fn=iou_bev, thresholds=thresholds)}
        for frame in frames:
            g = gt.get(frame, empty).select(name)
            p = pred.get(frame, empty).select(name)
            for a in acc.values():
                a.add_frame(p.boxes_cam, p.scores, g.boxes_cam)
        entry = {}
        for kind, field in (("3d", "ap3d"), ("bev", "apbev")):
            entry[field] = {threshold_key(t): none_if_nan(acc[kind].ap(t)) for t in thresholds}
            entry[field + "_r40"] = {threshold_key(t): none_if_nan(acc[kind].ap(t, "r40")) for t in thresholds}
            for t in thresholds:
                precision, recall, _ = acc[kind].curve(t)
                curves[(name, kind, threshold_key(t))] = (precision, recall)
        entry["num_gt"] = acc["3d"].num_gt
        entry["num_pred"] = acc["3d"].num_detections
        if entry["num_gt"] == 0:
            warnings.append(f"class {name!r} has no ground-truth box: its AP is undefined (null)")
        per_class[name] = entry
    metrics = {
        "detection": per_class,
        "detection_meta": {"pred_dir": os.path.abspath(pred_dir), "gt_dir": os.path.abspath(gt_dir),
                           "frames": len(frames), "iou_thresholds": [threshold_key(t) for t in thresholds],
                           "ap": "all-point interpolated (VOC); *_r40: KITTI 40 recall points",
                           "matching": MATCHING, "warnings": warnings},
    }
    return metrics, curves
