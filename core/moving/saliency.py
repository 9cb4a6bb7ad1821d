"""Center-surround motion saliency of a 3D box: the interior moves, the surrounding shell does not.

A 3D version of the 2D center-surround motion saliency score (paper §3, moving objects). Volumes are
Z×Y×X over the map grid; boxes are canonical (x, y, z, lx, ly, lz, yaw) in `ref` (docs/conventions.md#boxes).

score = mean(moving | interior) − mean(moving | shell), each mean weighted by `weight` (occupancy:
only matter can move; air has no flow to speak of), in [−1, 1]; higher is more salient. The shell
is the box grown by `shell_margin` metres on every side, minus the box. A region with no weight
contributes a mean of 0.
"""

from __future__ import annotations

import math

import numpy as np

from core.geometry.grid import GridConfig
from core.moving.components import to_numpy


def _inside_box(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Which of N×3 points lie inside the canonical box (7,)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # object -> frame
    local = (xyz - box[:3]) @ R                                  # N×3 = (Rᵀ (p − centre))ᵀ
    return np.all(np.abs(local) <= box[3:6] / 2, axis=1)


def box_interior_and_shell(box_ref, grid: GridConfig, *, shell_margin: float):
    """Voxels of `grid` whose centres lie in the box and in its shell.

    Returns (zyx M×3 int indices of the candidate block, interior M bool, shell M bool); only the
    block around the grown box is enumerated, so the cost is independent of the grid size.
    """
    box = np.asarray(box_ref, dtype=np.float64).reshape(7)
    grown = box.copy()
    grown[3:6] += 2 * shell_margin
    half = 0.5 * np.linalg.norm(grown[3:6][[0, 2]])              # BEV circumradius bounds x and z
    lo = np.array([grown[0] - half, grown[1] - grown[4] / 2, grown[2] - half])
    hi = np.array([grown[0] + half, grown[1] + grown[4] / 2, grown[2] + half])
    v = grid.voxel_size
    mins = np.array(grid.bounds_min)
    counts = np.array([grid.X, grid.Y, grid.Z])
    i_lo = np.clip(np.floor((lo - mins) / v - 0.5), 0, counts - 1).astype(int)  # (x, y, z) mem
    i_hi = np.clip(np.ceil((hi - mins) / v - 0.5), 0, counts - 1).astype(int)
    x, y, z = (np.arange(i_lo[d], i_hi[d] + 1) for d in range(3))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    zyx = np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1)     # M×3
    centres = (zyx[:, ::-1] + 0.5) * v + mins                        # M×3 (x, y, z) ref
    interior = _inside_box(centres, box)
    shell = _inside_box(centres, grown) & ~interior
    return zyx, interior, shell


def center_surround_score(moving, box_ref, grid: GridConfig, *, weight=None, shell_margin: float) -> float:
    """Saliency of one box: moving Z×Y×X in [0, 1] (e.g. 1 where the flow is over threshold),
    weight Z×Y×X ≥ 0 or None (uniform), box_ref (7,) canonical in `ref`. Returns a float in [−1, 1]."""
    mov = to_numpy(moving).astype(np.float64)
    w = np.ones_like(mov) if weight is None else to_numpy(weight).astype(np.float64)
    zyx, interior, shell = box_interior_and_shell(box_ref, grid, shell_margin=shell_margin)
    m = mov[zyx[:, 0], zyx[:, 1], zyx[:, 2]]
    ww = w[zyx[:, 0], zyx[:, 1], zyx[:, 2]]

    def weighted_mean(region: np.ndarray) -> float:
        total = ww[region].sum()
        return float((ww[region] * m[region]).sum() / total) if total > 0 else 0.0

    return weighted_mean(interior) - weighted_mean(shell)
