"""`n3dmap eval detection --pred DIR --gt DIR --out REPORT_DIR`: score KITTI-format label files.

One `<frame>.txt` per frame in each directory (see core.eval.kitti_labels); predictions carry a
score column. A frame with no prediction file has no detections; a prediction file with no
ground-truth file is a frame without objects (all its detections are false positives, and the
report warns). No 2D-size, truncation or occlusion filters: every ground-truth box of a class counts.

Writes REPORT_DIR/metrics.json, report.md and pr_curves.png. metrics.json holds, per class,
`detection.<class>.ap3d` and `.apbev`: maps from IoU threshold string ("0.33", "0.5", "0.75", and
any extra given) to all-point AP in [0, 1] (null where the class has no ground-truth box), plus
`ap3d_r40` / `apbev_r40` (KITTI R40), `num_gt` and `num_pred`.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from core.errors import DataError
from core.eval.average_precision import APAccumulator
from core.eval.iou3d import iou_3d, iou_bev
from core.eval.kitti_labels import FrameLabels, list_frames, read_label_file

DEFAULT_IOUS = (0.33, 0.5, 0.75)
IGNORED_TYPES = ("DontCare",)
MATCHING = ("greedy per frame, highest score first; a detection matches the unmatched ground-truth box "
            "of its class with the highest IoU if that IoU >= threshold; each ground-truth box at most once")


def threshold_key(t: float) -> str:
    """JSON key of an IoU threshold: 0.5 -> "0.5", 0.33 -> "0.33"."""
    return format(float(t), "g")


def _thresholds(ious) -> tuple[float, ...]:
    out = sorted({round(float(t), 6) for t in (*DEFAULT_IOUS, *(ious or ()))})
    bad = [t for t in out if not 0.0 < t <= 1.0]
    if bad:
        raise DataError(f"IoU thresholds must be in (0, 1], got {bad}")
    return tuple(out)


def _read_dir(directory: str, *, require_score: bool) -> dict[str, FrameLabels]:
    return {f: read_label_file(os.path.join(directory, f + ".txt"), require_score=require_score)
            for f in list_frames(directory)}


def evaluate_label_dirs(pred_dir: str, gt_dir: str, ious=None, classes=None) -> tuple[dict, dict]:
    """Score the predictions of `pred_dir` against `gt_dir`.

    Returns (metrics, curves): metrics as written to metrics.json; curves[(class, kind, key)] =
    (precision, recall) for the plots, kind in {"3d", "bev"}.
    """
    thresholds = _thresholds(ious)
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
            entry[field] = {threshold_key(t): _finite_or_none(acc[kind].ap(t)) for t in thresholds}
            entry[field + "_r40"] = {threshold_key(t): _finite_or_none(acc[kind].ap(t, "r40")) for t in thresholds}
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


def _finite_or_none(x: float):
    return None if math.isnan(x) else float(x)


def run_detection_files_eval(pred_dir: str, gt_dir: str, out_dir: str, ious=None, classes=None) -> dict:
    """Evaluate and write out_dir/metrics.json, report.md and pr_curves.png. Returns the metrics dict."""
    metrics, curves = evaluate_label_dirs(pred_dir, gt_dir, ious, classes)
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "metrics.json"), "w", encoding="utf-8") as f:
        json.dump(metrics, f, indent=2, allow_nan=False)
        f.write("\n")
    _plot_pr_curves(curves, os.path.join(out_dir, "pr_curves.png"))
    with open(os.path.join(out_dir, "report.md"), "w", encoding="utf-8") as f:
        f.write(_report_markdown(metrics))
    return metrics


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _report_markdown(metrics: dict) -> str:
    meta = metrics["detection_meta"]
    keys = meta["iou_thresholds"]
    lines = ["# 3D detection from KITTI label files", "",
             f"- predictions: `{meta['pred_dir']}`", f"- ground truth: `{meta['gt_dir']}`",
             f"- frames: {meta['frames']}", f"- AP: {meta['ap']}", f"- matching: {meta['matching']}",
             "- no 2D-size, truncation or occlusion filters", ""]
    header = "| class | GT | pred | " + " | ".join(f"AP3D@{k}" for k in keys) + " | " \
        + " | ".join(f"APBEV@{k}" for k in keys) + " |"
    lines += ["## All-point AP", "", header, "|" + "---|" * (3 + 2 * len(keys))]
    for name, e in metrics["detection"].items():
        lines.append(f"| {name} | {e['num_gt']} | {e['num_pred']} | "
                     + " | ".join(_fmt(e["ap3d"][k]) for k in keys) + " | "
                     + " | ".join(_fmt(e["apbev"][k]) for k in keys) + " |")
    lines += ["", "## KITTI R40 AP", "", header.replace("| class | GT | pred |", "| class | | |"),
              "|" + "---|" * (3 + 2 * len(keys))]
    for name, e in metrics["detection"].items():
        lines.append(f"| {name} | | | " + " | ".join(_fmt(e["ap3d_r40"][k]) for k in keys) + " | "
                     + " | ".join(_fmt(e["apbev_r40"][k]) for k in keys) + " |")
    lines += ["", "![precision-recall curves](pr_curves.png)", ""]
    if meta["warnings"]:
        lines += ["## Warnings", ""] + [f"- {w}" for w in meta["warnings"]] + [""]
    return "\n".join(lines)


def _plot_pr_curves(curves: dict, path: str) -> None:
    """Two panels (3D IoU, BEV IoU), one line per class × threshold."""
    fig = Figure(figsize=(11, 4.5))
    FigureCanvasAgg(fig)
    for ax, kind, title in zip(fig.subplots(1, 2), ("3d", "bev"), ("3D IoU", "BEV IoU")):
        for (name, k, key), (precision, recall) in curves.items():
            if k != kind or len(recall) == 0 or np.isnan(recall).any():
                continue
            # Start at recall 0 with the first precision so a one-point curve is still visible.
            ax.step(np.concatenate([[0.0], recall]), np.concatenate([precision[:1], precision]),
                    where="post", label=f"{name} @ {key}")
        ax.set(title=f"precision–recall, {title}", xlabel="recall", ylabel="precision",
               xlim=(0, 1.02), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
