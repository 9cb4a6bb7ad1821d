"""n3dmap arrays -> Rerun archetypes, with the conventions of rerun_paths (OpenCV frames, metres,
canonical boxes with yaw about Y). Pure numpy in, archetypes out; `rr` is the lazily imported SDK.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np


def yaw_quaternions(yaw: np.ndarray) -> np.ndarray:
    """N yaws (rad, about Y) -> N×4 quaternions in Rerun's (x, y, z, w) order.

    R = [[c,0,s],[0,1,0],[-s,0,c]] is the right-handed rotation by `yaw` about +Y, whose
    quaternion is (0, sin(yaw/2), 0, cos(yaw/2))."""
    half = 0.5 * np.asarray(yaw, np.float64).reshape(-1)
    q = np.zeros((half.size, 4), np.float32)  # N×4
    q[:, 1], q[:, 3] = np.sin(half), np.cos(half)
    return q


def boxes3d(rr, boxes: np.ndarray, *, colors, labels: Sequence[str] | None = None):
    """Canonical boxes N×7 (x, y, z, lx, ly, lz, yaw) in the entity's frame -> rr.Boxes3D.
    `colors`: one RGB for all or N×3. An empty N gives an empty entry (a frame with no boxes)."""
    boxes = np.asarray(boxes, np.float32).reshape(-1, 7)  # N×7
    n = boxes.shape[0]
    colors = np.asarray(colors, np.uint8)
    colors = np.broadcast_to(colors, (n, 3)) if colors.ndim == 1 else colors.reshape(n, 3)
    return rr.Boxes3D(centers=boxes[:, :3], half_sizes=0.5 * boxes[:, 3:6], quaternions=yaw_quaternions(boxes[:, 6]),
                      colors=colors, labels=list(labels) if labels is not None else None,
                      show_labels=labels is not None and n > 0)


def transform(rr, parent_T_child: np.ndarray):
    """4×4 rigid pose parent_T_child -> rr.Transform3D logged at the child entity."""
    m = np.asarray(parent_T_child, np.float64)
    return rr.Transform3D(translation=m[:3, 3].astype(np.float32), mat3x3=m[:3, :3].astype(np.float32))


def pinhole(rr, pix_T_cam: np.ndarray, *, height: int, width: int, image_plane_distance: float = 1.0):
    """4×4 intrinsics (fx=[0,0], fy=[1,1], cx=[0,2], cy=[1,2]) of an H×W OpenCV camera -> rr.Pinhole.
    The viewer back-projects a DepthImage logged beside it and draws the frustum
    `image_plane_distance` metres deep."""
    k = np.asarray(pix_T_cam, np.float32)[:3, :3]
    return rr.Pinhole(image_from_camera=k, resolution=[width, height], camera_xyz=rr.ViewCoordinates.RDF,
                      image_plane_distance=image_plane_distance)


def grid_box(rr, grid: Mapping[str, float]):
    """The map grid's bounds (GridConfig.to_dict()) as one grey box in `ref`."""
    from services.viz import rerun_paths as paths

    lo = np.array([grid["xmin"], grid["ymin"], grid["zmin"]], np.float32)
    hi = np.array([grid["xmax"], grid["ymax"], grid["zmax"]], np.float32)
    return rr.Boxes3D(centers=[(lo + hi) / 2], half_sizes=[(hi - lo) / 2], colors=[paths.GRID_BOX],
                      labels=[f"map grid {grid['Z']}×{grid['Y']}×{grid['X']}"], show_labels=False)


def voxel_centres_ref(zyx: np.ndarray, grid: Mapping[str, float]) -> np.ndarray:
    """N×3 voxel indices (z, y, x) -> N×3 centres (x, y, z) in ref metres: ref = (mem + 0.5)·voxel + min."""
    voxel = (grid["xmax"] - grid["xmin"]) / grid["X"]
    xyz_mem = np.asarray(zyx, np.float64)[:, ::-1]  # N×3 (x, y, z)
    return ((xyz_mem + 0.5) * voxel + np.array([grid["xmin"], grid["ymin"], grid["zmin"]])).astype(np.float32)


def speed_colors(magnitude: np.ndarray, vmax: float, cmap: str = "turbo") -> np.ndarray:
    """N magnitudes -> N×3 uint8 colours of `cmap` over [0, vmax] (clipped)."""
    from matplotlib import colormaps

    x = np.clip(np.asarray(magnitude, np.float64) / max(float(vmax), 1e-9), 0.0, 1.0)
    return (colormaps[cmap](x)[:, :3] * 255).round().astype(np.uint8)  # N×3


def depth_points(depth: np.ndarray, pix_T_cam: np.ndarray) -> np.ndarray:
    """H×W depth (metres along Z, 0 = none) -> N×3 points in the camera frame, one per valid pixel."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    fx, fy, cx, cy = pix_T_cam[0, 0], pix_T_cam[1, 1], pix_T_cam[0, 2], pix_T_cam[1, 2]
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1).astype(np.float32)  # N×3
