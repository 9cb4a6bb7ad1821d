"""Point-to-plane ICP: the geometric egomotion baseline on two point clouds (numpy + scipy KD-tree).

Conventions (docs/conventions.md#poses): point sets are N×3 (x, y, z) in metres; the result is `target_T_source`
(p_target = target_T_source @ p_source), 4×4 float64. For egomotion between frames 0 and 1 with clouds in
`ref0` and `ref1`, pass source = cloud of frame 1, target = cloud of frame 0 to get `ref0_T_ref1`.

Each iteration: match every source point to its nearest target point (KD-tree), drop pairs farther than
`max_distance`, and solve the linearised point-to-plane least squares
    min_x Σ ((p_i × n_i)·ω + n_i·t − n_i·(q_i − p_i))²,  x = (ω, t)
(small-angle rotation ω), then apply exp(ω) exactly (Rodrigues) and compose. Target normals come from
PCA of each target point's `normal_neighbors` nearest neighbours (smallest-eigenvalue eigenvector).

`icp_coarse_to_fine` runs it with a shrinking correspondence gate, each stage from the last one's pose (as
Open3D's multi-scale ICP does): a loose gate finds the pose, a tight one keeps wrong matches (a moving car,
a surface one frame does not see) out of the final least squares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from core.errors import ShapeError


@dataclass(frozen=True)
class IcpResult:
    target_T_source: np.ndarray  # 4×4 float64
    iterations: int
    rmse: float                  # point-to-plane residual RMS (metres) over the last step's inliers, as its linear
                                 # solve predicts it after that step's update (not re-measured at the returned pose)
    inlier_fraction: float


def _check_cloud(name: str, xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ShapeError(f"{name}: expected shape N×3, got {'×'.join(map(str, xyz.shape))}")
    if not np.isfinite(xyz).all():
        raise ShapeError(f"{name}: points must be finite")
    return xyz


def estimate_normals(xyz: np.ndarray, *, neighbors: int = 10, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals N×3 by PCA of the `neighbors` nearest points (sign arbitrary). xyz: N×3."""
    xyz = _check_cloud("xyz", xyz)
    k = min(neighbors, len(xyz))
    tree = tree if tree is not None else cKDTree(xyz)
    _, idx = tree.query(xyz, k=k)
    idx = idx.reshape(len(xyz), k)  # N×k
    nb = xyz[idx]  # N×k×3
    centered = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centered, centered)  # N×3×3
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    return vecs[:, :, 0]  # N×3


def _rodrigues(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta ** 2 * (K @ K)


def voxel_downsample(xyz: np.ndarray, voxel: float) -> np.ndarray:
    """One point (the mean) per occupied cube of edge `voxel` metres. xyz: N×3 -> M×3."""
    xyz = _check_cloud("xyz", xyz)
    if voxel <= 0 or len(xyz) == 0:
        return xyz
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.reshape(-1), xyz)
    return sums / counts[:, None]


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, *, init: np.ndarray | None = None,
                       iterations: int = 30, max_distance: float = 1.0, normal_neighbors: int = 10,
                       tolerance: float = 1e-6) -> IcpResult:
    """Align `source` (N×3) to `target` (M×3); returns `target_T_source` (4×4) and fit statistics.

    init: 4×4 starting target_T_source (identity if None). max_distance: correspondences farther than
    this (metres) are ignored. Stops when the update is below `tolerance` (radians + metres).
    """
    src = _check_cloud("source", source)
    tgt = _check_cloud("target", target)
    if len(src) < 6 or len(tgt) < 6:
        raise ShapeError(f"icp_point_to_plane: need at least 6 points per cloud, got {len(src)} and {len(tgt)}")
    T = np.eye(4) if init is None else np.asarray(init, dtype=np.float64).copy()
    tree = cKDTree(tgt)
    normals = estimate_normals(tgt, neighbors=normal_neighbors, tree=tree)
    rmse, inliers, it = float("nan"), 0.0, 0
    for it in range(1, iterations + 1):
        p = src @ T[:3, :3].T + T[:3, 3]  # N×3 source in target frame
        dist, idx = tree.query(p, k=1)
        keep = dist < max_distance
        inliers = float(keep.mean())
        if keep.sum() < 6:
            break
        p, q, n = p[keep], tgt[idx[keep]], normals[idx[keep]]
        A = np.concatenate([np.cross(p, n), n], axis=1)  # K×6
        b = np.einsum("ki,ki->k", n, q - p)  # K
        x, *_ = np.linalg.lstsq(A, b, rcond=None)
        rmse = float(np.sqrt(np.mean((A @ x - b) ** 2)))
        step = np.eye(4)
        step[:3, :3] = _rodrigues(x[:3])
        step[:3, 3] = x[3:]
        T = step @ T
        if np.abs(x).sum() < tolerance:
            break
    return IcpResult(target_T_source=T, iterations=it, rmse=rmse, inlier_fraction=inliers)


def icp_coarse_to_fine(source: np.ndarray, target: np.ndarray, *, max_distances: tuple[float, ...],
                       init: np.ndarray | None = None, iterations: int = 30, normal_neighbors: int = 10,
                       tolerance: float = 1e-6) -> IcpResult:
    """`icp_point_to_plane` once per gate of `max_distances` (metres, decreasing), each stage starting from
    the previous stage's pose; returns the last stage's result with `iterations` summed over the stages."""
    if not max_distances or any(b > a for a, b in zip(max_distances, max_distances[1:])) or min(max_distances) <= 0:
        raise ValueError(f"max_distances must be positive and non-increasing, got {list(max_distances)}")
    result, total = None, 0
    for gate in max_distances:
        result = icp_point_to_plane(source, target, init=init if result is None else result.target_T_source,
                                    iterations=iterations, max_distance=gate, normal_neighbors=normal_neighbors,
                                    tolerance=tolerance)
        total += result.iterations
    return IcpResult(target_T_source=result.target_T_source, iterations=total, rmse=result.rmse,
                     inlier_fraction=result.inlier_fraction)
