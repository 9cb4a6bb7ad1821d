"""Ground plane: fitted to one frame's depth points, so that voxels at or below it never count as moving.

Why: measured on tiny held-out pairs (24-record chain, 8 val records), most voxels that the learned
3D flow calls moving but that lie outside every moving object (40–157 of 59–266 per pair, at 1 voxel
and 2 voxels from the cars) sit in the ground layer around the moving cars: a car that moves changes
what the ground voxels beside it look like, and the flow copies the car's motion there. Those voxels
join the car's component, so its box grows by a metre or two and misses the IoU bar. Nothing that
moves lies below the ground, so the post-processing drops the voxels whose centre lies less than
`margin` voxels above the fitted plane (the voxel holding the ground surface, unless the surface lies in
its bottom quarter, and everything under it).

Conventions (docs/conventions.md#frames): points in `ref`, metres, y down; the plane is (a, b, c, d) with unit
normal n = (a, b, c) pointing UP (n · (0, −1, 0) > 0) and height(p) = n · p + d (metres above the
ground). RANSAC: random point triplets, the plane with the most inliers among those tilted at most
`max_tilt_deg` from ref's horizontal (45° by default: when ref is a camera looking down, as in the
synthetic rig at 10–40° elevation, the ground tilts that much in it) and lying below the rig origin (d > 0: the cameras look at the ground
from above), then a least-squares refit to its inliers. Deterministic for a given `seed`.
"""

from __future__ import annotations

import math

import numpy as np

from core.geometry.grid import GridConfig

UP = np.array([0.0, -1.0, 0.0])  # y points down in ref
# A quarter voxel, not half: where the ground lies exactly on a voxel face (the synthetic world's does),
# the voxel just above it has its centre half a voxel up, and a fitted plane's rounding would drop it
# at a half-voxel margin (measured: the oracle's car boxes lost their bottom layer, AP3D@0.5 0.89 -> 0).
DEFAULT_MARGIN_VOXELS = 0.25


def _plane_through(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p: K×3×3 triplets -> (normals K×3, unit, pointing up; offsets K) of their planes (NaN if degenerate)."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # K×3
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    n = np.where((n @ UP)[:, None] < 0, -n, n)  # point up
    return n, -(n * p[:, 0]).sum(axis=1)


def fit_ground_plane(points: np.ndarray, *, max_tilt_deg: float = 45.0, inlier_distance: float = 0.1,
                     iterations: int = 256, max_points: int = 4096, min_inliers: int = 50,
                     seed: int = 0) -> np.ndarray | None:
    """points: N×3 in ref (metres, y down) -> the ground plane (4,) = (a, b, c, d), or None when no
    near-horizontal plane below the origin holds `min_inliers` of the (subsampled) points."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < max(3, min_inliers):
        return None
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]  # M×3
    triplets = pts[rng.integers(0, len(pts), size=(iterations, 3))]  # K×3×3
    normals, offsets = _plane_through(triplets)  # K×3, K
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    ok = np.isfinite(normals).all(axis=1) & (normals @ UP >= cos_tilt) & (offsets > 0)
    if not ok.any():
        return None
    normals, offsets = normals[ok], offsets[ok]
    inliers = np.abs(pts @ normals.T + offsets) <= inlier_distance  # M×K'
    best = int(inliers.sum(axis=0).argmax())
    members = pts[inliers[:, best]]
    if len(members) < min_inliers:
        return None
    # Least-squares refit: the normal is the direction of least spread of the inliers.
    centre = members.mean(axis=0)
    normal = np.linalg.svd(members - centre, full_matrices=False)[2][-1]
    if normal @ UP < 0:
        normal = -normal
    if normal @ UP < cos_tilt:  # the refit tilted away: keep the RANSAC plane
        normal, d = normals[best], offsets[best]
    else:
        d = -float(normal @ centre)
    return np.array([*normal, d])


def ground_y_at(plane: np.ndarray, x: float, z: float) -> float:
    """The y (metres, down) of the plane at horizontal position (x, z) in ref."""
    a, b, c, d = (float(v) for v in plane)
    return -(a * x + c * z + d) / b


def voxel_heights(grid: GridConfig, plane: np.ndarray) -> np.ndarray:
    """Height above `plane` (metres) of every voxel centre of `grid`: Z×Y×X."""
    def centres(lo: float, hi: float, n: int) -> np.ndarray:
        return lo + (np.arange(n) + 0.5) * (hi - lo) / n
    x = centres(grid.xmin, grid.xmax, grid.X)[None, None, :]
    y = centres(grid.ymin, grid.ymax, grid.Y)[None, :, None]
    z = centres(grid.zmin, grid.zmax, grid.Z)[:, None, None]
    a, b, c, d = (float(v) for v in plane)
    return a * x + b * y + c * z + d  # Z×Y×X


def above_ground(grid: GridConfig, plane: np.ndarray | None, *, margin_voxels: float = DEFAULT_MARGIN_VOXELS) -> np.ndarray | None:
    """Z×Y×X bool: voxel centres at least `margin_voxels` voxels above the plane (None without a plane)."""
    if plane is None:
        return None
    return voxel_heights(grid, plane) >= margin_voxels * grid.voxel_size
