"""Figures shared by the box evaluations (detection, moving objects): precision-recall plots and
bird's-eye views of boxes over a map image (Agg, no display). Their AP is core.eval.method_ap's.

Boxes are canonical (x, y, z, lx, ly, lz, yaw) rows in the map frame `ref` (docs/conventions.md#boxes); the
bird's-eye view is the (x, z) plane seen from above (x right, z up the page).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from core.geometry.grid import GridConfig
from services.viz.preview import bev_footprint


def pr_figure(curves: dict[str, tuple[np.ndarray, np.ndarray]], *, title: str) -> Figure:
    """One panel: a step curve per name -> (precision, recall)."""
    fig = Figure(figsize=(5.5, 4.2))
    ax = fig.subplots()
    for name, (precision, recall) in curves.items():
        if len(recall) == 0 or np.isnan(recall).any():
            ax.plot([], [], label=f"{name} (no detections)")
            continue
        # start at recall 0 with the first precision so a one-point curve is still visible
        ax.step(np.concatenate([[0.0], recall]), np.concatenate([precision[:1], precision]), where="post",
                label=name)
    ax.set(title=title, xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return fig


def bev_boxes_figure(grid: GridConfig, panels: list[tuple[str, np.ndarray | None, np.ndarray, np.ndarray]],
                     *, image_label: str = "", suptitle: str = "") -> Figure:
    """Bird's-eye panels over the grid, each (title, image Z×X or None, gt_boxes G×7, pred_boxes D×7)
    with boxes in ref: the image (e.g. |flow| max over height) under the boxes on one colour scale,
    ground truth green, predictions red."""
    fig = Figure(figsize=(4.0 * len(panels) + 0.8, 4.0))
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    extent = (grid.xmin, grid.xmax, grid.zmin, grid.zmax)
    images = [p[1] for p in panels if p[1] is not None]
    vmax = max([float(np.nanmax(i)) for i in images] + [1e-6])
    shown = None
    for ax, (title, image, gt, pred) in zip(axes, panels):
        if image is not None:
            shown = ax.imshow(image, origin="lower", extent=extent, cmap="magma", vmin=0.0, vmax=vmax)
        for boxes, colour in ((gt, "lime"), (pred, "red")):
            for box in np.asarray(boxes, dtype=np.float64).reshape(-1, 7):
                corners = bev_footprint(box)
                closed = np.vstack([corners, corners[:1]])
                ax.plot(closed[:, 0], closed[:, 1], color=colour, linewidth=1.2)
        ax.set(title=title, xlabel="x (m, ref)", ylabel="z (m, ref)", xlim=(grid.xmin, grid.xmax),
               ylim=(grid.zmin, grid.zmax))
        ax.set_aspect("equal")
    if shown is not None:
        fig.colorbar(shown, ax=list(axes), shrink=0.75, label=image_label)
    if suptitle:
        fig.suptitle(suptitle)
    return fig
