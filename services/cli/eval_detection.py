"""`n3dmap eval detection --pred DIR --gt DIR --out REPORT_DIR`: score KITTI-format label files.

The scoring is core.eval.protocols.label_files (which frames and boxes count, AP, warnings); this
module writes REPORT_DIR/metrics.json, report.md and pr_curves.png. metrics.json holds, per class,
`detection.<class>.ap3d` and `.apbev`: maps from IoU threshold string ("0.33", "0.5", "0.75", and
any extra given) to all-point AP in [0, 1] (null where the class has no ground-truth box), plus
`ap3d_r40` / `apbev_r40` (KITTI R40), `num_gt` and `num_pred`.
"""

from __future__ import annotations

import json
import os

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from core.eval.protocols.label_files import evaluate_label_dirs


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
