"""Oriented box fit: minimum-area rectangle in bird's-eye view × vertical extent.

Conventions (docs/conventions.md#boxes): points are N×3 (x, y, z) in a camera-like frame (X right, Y down,
Z forward). The bird's-eye view is the (x, z) plane and "vertical" is Y. Boxes come out in the
canonical encoding (x, y, z, lx, ly, lz, yaw) of that same frame: the object's x axis is the
direction (cos yaw, −sin yaw) in (x, z), lx ≥ lz (length is the longer side), yaw in [−π/2, π/2).

The minimum-area enclosing rectangle has a side collinear with an edge of the convex hull
(Freeman & Shapira 1975, the fact rotating calipers rest on); we try every hull edge at once in
vectorised form, which finds the same rectangle as a caliper sweep.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from core.errors import ShapeError
from core.geometry.grid import GridConfig


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """Hull vertices (H×2, counter-clockwise) of N×2 points; degenerate sets return their extremes."""
    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)
    if len(pts) < 3:
        return pts
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:
        # Collinear points: the "hull" is the segment between the two extreme points.
        direction = pts[-1] - pts[0]
        t = pts @ direction
        return pts[[int(np.argmin(t)), int(np.argmax(t))]]


def min_area_rectangle(points: np.ndarray):
    """Minimum-area rectangle around N×2 points (columns (x, z)).

    Returns (centre 2, axis 2, extent 2): `axis` is the unit direction of one side, `extent` the
    rectangle's lengths along `axis` and along its perpendicular (−axis[1], axis[0]).
    """
    hull = convex_hull_2d(points)
    if len(hull) == 0:
        raise ShapeError("min_area_rectangle: no points")
    if len(hull) == 1:
        return hull[0].copy(), np.array([1.0, 0.0]), np.zeros(2)
    edges = np.roll(hull, -1, axis=0) - hull                     # H×2
    lengths = np.linalg.norm(edges, axis=1)
    keep = lengths > 0
    axes = edges[keep] / lengths[keep, None]                     # E×2 unit edge directions
    perps = np.stack([-axes[:, 1], axes[:, 0]], axis=1)          # E×2, det(axis, perp) = +1
    proj_a = hull @ axes.T                                       # H×E
    proj_p = hull @ perps.T                                      # H×E
    span_a = proj_a.max(0) - proj_a.min(0)
    span_p = proj_p.max(0) - proj_p.min(0)
    best = int(np.argmin(span_a * span_p))
    mid_a = 0.5 * (proj_a[:, best].max() + proj_a[:, best].min())
    mid_p = 0.5 * (proj_p[:, best].max() + proj_p[:, best].min())
    centre = mid_a * axes[best] + mid_p * perps[best]
    return centre, axes[best], np.array([span_a[best], span_p[best]])


def l_shape_rectangle(points: np.ndarray, *, floor: float, step_deg: float = 1.0):
    """Rectangle around N×2 points (x, z) of a surface seen from one side: the orientation whose
    rectangle has the most points close to its edges (the "closeness" criterion of Zhang et al.,
    "Efficient L-shape fitting for vehicle detection using laser scanners", IV 2017).

    The minimum-area rectangle of an L (two faces of a box) is often aligned with the L's hypotenuse;
    closeness puts both legs on edges. Each point counts 1 / max(distance to its nearer edge, `floor`)
    (floor: metres, about the points' quantisation), with the nearer of the two parallel edges chosen
    per axis for the whole set. Returns (centre 2, axis 2, extent 2) as min_area_rectangle.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise ShapeError(f"l_shape_rectangle: expected N×2 points with N ≥ 1, got {pts.shape}")
    if len(np.unique(pts, axis=0)) < 3:
        return min_area_rectangle(pts)
    theta = np.deg2rad(np.arange(0.0, 90.0, step_deg))                 # A angles: a rectangle repeats every 90°
    axes = np.stack([np.cos(theta), np.sin(theta)], axis=1)            # A×2
    perps = np.stack([-axes[:, 1], axes[:, 0]], axis=1)                # A×2
    hugged = []
    for proj in (pts @ axes.T, pts @ perps.T):                          # N×A each
        to_max = proj.max(0) - proj                                     # N×A distance to the far edge
        to_min = proj - proj.min(0)
        # The edge the points hug: the one with the smaller total distance, for the whole set.
        use_max = np.linalg.norm(to_max, axis=0) < np.linalg.norm(to_min, axis=0)
        hugged.append(np.where(use_max[None], to_max, to_min))          # N×A
    dist = np.minimum(hugged[0], hugged[1])                             # N×A: to the nearer hugged edge
    best = int(np.argmax((1.0 / np.maximum(dist, floor)).sum(0)))
    a, p = axes[best], perps[best]
    ca, cp = pts @ a, pts @ p
    centre = 0.5 * (ca.max() + ca.min()) * a + 0.5 * (cp.max() + cp.min()) * p
    return centre, a, np.array([ca.max() - ca.min(), cp.max() - cp.min()])


def fit_box_to_points(xyz: np.ndarray, *, pad: float = 0.0, l_shape_floor: float | None = None,
                      min_extent: float = 0.0) -> np.ndarray:
    """Canonical box (7,) around N×3 points of one frame; every side grows by `pad` metres and is at least
    `min_extent` metres.

    `pad` accounts for the support of each sample: points at voxel centres need pad = voxel size
    to cover their voxels. `min_extent`: voxel centres of a surface seen within one voxel layer span 0 m
    across it, though the surface may lie anywhere in that voxel: a side is at least one voxel then.
    l_shape_floor: None — the minimum-area rectangle; a distance in metres —
    the L-shape (closeness) rectangle, for points on the visible faces of an object (l_shape_rectangle).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise ShapeError(f"fit_box_to_points: expected N×3 with N ≥ 1, got {'×'.join(map(str, xyz.shape))}")
    if l_shape_floor is None:
        centre_xz, axis, extent = min_area_rectangle(xyz[:, [0, 2]])
    else:
        centre_xz, axis, extent = l_shape_rectangle(xyz[:, [0, 2]], floor=l_shape_floor)
    if extent[1] > extent[0]:
        # Make the longer side the object's x axis (length); the new x axis is the old perpendicular.
        axis = np.array([-axis[1], axis[0]])
        extent = extent[::-1]
    # Object x axis = (cos yaw, −sin yaw) in (x, z).
    yaw = math.atan2(-axis[1], axis[0])
    yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2             # a box is symmetric under yaw + π
    y_lo, y_hi = xyz[:, 1].min(), xyz[:, 1].max()
    return np.array([centre_xz[0], 0.5 * (y_lo + y_hi), centre_xz[1], max(extent[0] + pad, min_extent),
                     max(y_hi - y_lo + pad, min_extent), max(extent[1] + pad, min_extent), yaw])


def voxel_indices_to_ref(zyx: np.ndarray, grid: GridConfig) -> np.ndarray:
    """Voxel indices N×3 in (z, y, x) order -> their centres N×3 (x, y, z) in `ref` metres."""
    zyx = np.asarray(zyx, dtype=np.float64)
    mem_xyz = zyx[:, ::-1]                                        # N×3 (x, y, z) mem
    return (mem_xyz + 0.5) * grid.voxel_size + np.array(grid.bounds_min)


def fit_box_to_voxels(zyx: np.ndarray, grid: GridConfig) -> np.ndarray:
    """Canonical box (7,) in `ref` covering the voxels with indices N×3 (z, y, x) of `grid`."""
    return fit_box_to_points(voxel_indices_to_ref(zyx, grid), pad=grid.voxel_size)
