"""Contact sheet of one record: RGB and depth of every view at the first and last step, plus a
bird's-eye view of the boxes and cameras in `ref` at t=0.

Frames (docs/conventions.md#frames): cameras are OpenCV (X right, Y down, Z forward); boxes are rows
(x, y, z, lx, ly, lz, yaw) in `world` with yaw about Y, R = [[c,0,s],[0,1,0],[-s,0,c]].
The bird's-eye view plots ref x to the right and ref z (forward) up; it is drawn in `ref` at t=0, so
boxes of t=0 and t+1 and the camera centres are all moved into that one frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from matplotlib.figure import Figure
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.patches import Polygon, Rectangle

# Points drawn per view in the bird's-eye view (a random subset of the valid depth pixels).
_BEV_POINTS_PER_VIEW = 3000


def _yaw_of(R: np.ndarray) -> float:
    """Yaw about Y of a 3×3 rotation (reads R[0,2] = sin, R[0,0] = cos)."""
    return float(np.arctan2(R[0, 2], R[0, 0]))


def boxes_in_frame(a_T_b: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Move boxes K×7 from frame b to frame a (4×4 whose rotation is about Y): centres transform,
    yaw adds the rotation's yaw. Returns K×7."""
    out = boxes_b.astype(np.float64).copy()
    out[:, :3] = boxes_b[:, :3] @ a_T_b[:3, :3].T + a_T_b[:3, 3]
    out[:, 6] = boxes_b[:, 6] + _yaw_of(a_T_b[:3, :3])
    return out


def bev_footprint(box: np.ndarray) -> np.ndarray:
    """4×2 (x, z) corners of one box's footprint (x, y, z, lx, ly, lz, yaw), in drawing order."""
    x, _, z, lx, _, lz, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    dx = np.array([1, 1, -1, -1]) * lx / 2      # object x offsets
    dz = np.array([1, -1, -1, 1]) * lz / 2      # object z offsets
    # p = R·(dx, 0, dz): x' = c·dx + s·dz, z' = -s·dx + c·dz
    return np.stack([x + c * dx + s * dz, z - s * dx + c * dz], axis=1)  # 4×2


def _depth_points(depth: np.ndarray, pix_T_cam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """N×3 camera points from a subset of the valid pixels of an H×W depth image."""
    v, u = np.nonzero(depth > 0)
    if len(u) > _BEV_POINTS_PER_VIEW:
        pick = rng.choice(len(u), _BEV_POINTS_PER_VIEW, replace=False)
        u, v = u[pick], v[pick]
    z = depth[v, u]
    fx, fy, cx, cy = pix_T_cam[0, 0], pix_T_cam[1, 1], pix_T_cam[0, 2], pix_T_cam[1, 2]
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)  # N×3


def contact_sheet(record: Mapping[str, np.ndarray], out_path: str | Path, *, title: str = "",
                  grid: Mapping | None = None, dpi: int = 100) -> Path:
    """Write a PNG contact sheet of `record` (a validated record dict) to `out_path`.

    Rows: views v = 0..V-1. Columns: RGB t=0, depth t=0, RGB t=T-1, depth t=T-1 (the last two only
    when T > 1), and a bird's-eye view spanning all rows: depth points of t=0 (grey), box footprints
    at t=0 (moving boxes red, with an arrow to their centre and a dashed footprint at t+1), camera
    centres and viewing
    directions, and the map grid's x/z bounds when `grid` (GridConfig.to_dict()) is given.
    """
    rgb, depth = record["rgb"], record["depth"]                  # T×V×H×W×3, T×V×H×W
    T, V, H, W, _ = rgb.shape
    steps = [0] if T == 1 else [0, T - 1]
    image_cols = 2 * len(steps)
    aspect = W / H
    cell_w = 2.6 * aspect ** 0.5
    cell_h = cell_w / aspect
    fig = Figure(figsize=(cell_w * image_cols + 6.5, max(cell_h * V + 0.8, 6.0)), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    spec = fig.add_gridspec(V, image_cols + 1, width_ratios=[cell_w] * image_cols + [6.0])

    valid_depth = depth[depth > 0]
    vmax = float(np.percentile(valid_depth, 99)) if valid_depth.size else 1.0
    for v in range(V):
        for j, t in enumerate(steps):
            ax = fig.add_subplot(spec[v, 2 * j])
            ax.imshow(rgb[t, v])
            ax.set_axis_off()
            ax.set_title(f"rgb t={t} v={v}", fontsize=8)
            ax = fig.add_subplot(spec[v, 2 * j + 1])
            shown = np.ma.masked_equal(depth[t, v], 0.0)
            ax.imshow(shown, cmap="viridis", vmin=0.0, vmax=vmax, interpolation="nearest")
            ax.set_facecolor("black")
            ax.set_axis_off()
            ax.set_title(f"depth t={t} v={v} (0–{vmax:.0f} m)", fontsize=8)

    ax = fig.add_subplot(spec[:, image_cols])
    _draw_bev(ax, record, grid)
    if title:
        fig.suptitle(title, fontsize=10)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path)
    return out_path


def _draw_bev(ax, record: Mapping[str, np.ndarray], grid: Mapping | None) -> None:
    T = record["rgb"].shape[0]
    V = record["rgb"].shape[1]
    ref0_T_world = np.linalg.inv(record["world_T_ref"][0].astype(np.float64))
    rng = np.random.default_rng(0)

    for v in range(V):
        ref0_T_cam = ref0_T_world @ record["world_T_cam"][0, v]
        xyz_cam = _depth_points(record["depth"][0, v], record["pix_T_cam"][v], rng)
        xyz_ref = xyz_cam @ ref0_T_cam[:3, :3].T + ref0_T_cam[:3, 3]   # N×3
        ax.scatter(xyz_ref[:, 0], xyz_ref[:, 2], s=0.3, c="0.6", linewidths=0)
    centres_xz = []
    for v in range(V):
        ref0_T_cam = ref0_T_world @ record["world_T_cam"][0, v]
        centre, forward = ref0_T_cam[:3, 3], ref0_T_cam[:3, 2]
        centres_xz.append(centre[[0, 2]])
        ax.plot(centre[0], centre[2], marker="o", color="tab:blue", ms=4)
        ax.plot([centre[0], centre[0] + 2.0 * forward[0]], [centre[2], centre[2] + 2.0 * forward[2]],
                color="tab:blue", lw=1)
        ax.annotate(f"cam{v}", (centre[0], centre[2]), fontsize=7, color="tab:blue",
                    xytext=(3, 3), textcoords="offset points")

    boxes0 = boxes_in_frame(ref0_T_world, record["boxes"][0])
    boxes1 = boxes_in_frame(ref0_T_world, record["boxes"][1]) if T > 1 else None
    valid, moving, ids = record["box_valid"], record["box_moving"], record["box_id"]
    for k in range(boxes0.shape[0]):
        if not valid[0, k]:
            continue
        color = "tab:red" if moving[k] else "tab:green"
        ax.add_patch(Polygon(bev_footprint(boxes0[k]), closed=True, fill=False, edgecolor=color, lw=1.2))
        ax.annotate(str(int(ids[k])), (boxes0[k, 0], boxes0[k, 2]), fontsize=7, color=color, ha="center")
        if moving[k] and boxes1 is not None and valid[1, k]:
            start, end = boxes0[k, [0, 2]], boxes1[k, [0, 2]]
            ax.add_patch(Polygon(bev_footprint(boxes1[k]), closed=True, fill=False, edgecolor=color,
                                 lw=0.8, ls="--"))
            ax.annotate("", xy=end, xytext=start,
                        arrowprops=dict(arrowstyle="->", color="tab:red", lw=1.2))
    if grid is not None:
        ax.add_patch(Rectangle((grid["xmin"], grid["zmin"]), grid["xmax"] - grid["xmin"],
                               grid["zmax"] - grid["zmin"], fill=False, ls="--", edgecolor="0.3", lw=0.8))
    # Frame the grid, the cameras and the boxes; far depth points (sky, distant walls) would shrink them.
    extent = [(xz[0], xz[1]) for xz in centres_xz]
    extent += [tuple(c) for k in range(boxes0.shape[0]) if valid[0, k] for c in bev_footprint(boxes0[k])]
    if grid is not None:
        extent += [(grid["xmin"], grid["zmin"]), (grid["xmax"], grid["zmax"])]
    if extent:
        pts = np.array(extent, np.float64)
        lo, hi = pts.min(axis=0) - 3.0, pts.max(axis=0) + 3.0
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("ref x (m, right)")
    ax.set_ylabel("ref z (m, forward)")
    ax.set_title("bird's-eye view, ref at t=0\n(green static, red moving, dashed at t+1; ● cameras, line = forward)", fontsize=8)
    ax.grid(True, lw=0.3)
