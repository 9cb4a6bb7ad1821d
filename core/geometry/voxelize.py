"""Point clouds to binary occupancy volumes.

Conventions (docs/conventions.md#the-map-grid): points B×N×3 in (x, y, z) order, metres in `ref` (OpenCV-like:
X right, Y down, Z forward); volumes B×C×Z×Y×X. `mem = (ref − min)/voxel − 0.5`, so integer mem are voxel
centres and voxel (i, j, k) covers mem x in [i−0.5, i+0.5) (likewise y, z); a point goes to the voxel whose
centre is nearest (floor(mem + 0.5)). Points outside the grid are dropped.
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref


def points_to_voxel_index(xyz_ref: torch.Tensor, grid: GridConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """xyz_ref: B×N×3 -> (flat index z·Y·X + y·X + x: B×N int64, inside: B×N bool)."""
    check_shape("xyz_ref", xyz_ref, (None, None, 3))
    B = xyz_ref.shape[0]
    mem = se3.apply(mem_T_ref(grid, dtype=xyz_ref.dtype, device=xyz_ref.device).expand(B, 4, 4), xyz_ref)  # B×N×3
    ijk = torch.floor(mem + 0.5)  # B×N×3 nearest centre, still float so NaN/inf stay detectable
    size = torch.tensor([grid.X, grid.Y, grid.Z], dtype=ijk.dtype, device=ijk.device)
    inside = ((ijk >= 0) & (ijk < size)).all(-1)  # NaNs compare False -> dropped
    ijk = torch.where(inside.unsqueeze(-1), ijk, torch.zeros_like(ijk)).long()
    flat = (ijk[..., 2] * grid.Y + ijk[..., 1]) * grid.X + ijk[..., 0]
    return flat, inside


def voxelize(xyz_ref: torch.Tensor, grid: GridConfig, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Binary occupancy of the voxels that contain at least one (valid) point.

    xyz_ref: B×N×3 (metres, ref), valid: B×N bool or None -> B×1×Z×Y×X float in {0, 1} (dtype of xyz_ref).
    Not differentiable (a scatter of ones).
    """
    B, N = xyz_ref.shape[:2]
    flat, keep = points_to_voxel_index(xyz_ref, grid)
    if valid is not None:
        check_shape("valid", valid, (B, N))
        keep = keep & valid.bool()
    n_vox = grid.Z * grid.Y * grid.X
    flat = torch.where(keep, flat, torch.full_like(flat, n_vox))  # dropped points go to a spare slot
    dtype = xyz_ref.dtype if xyz_ref.is_floating_point() else torch.float32
    occ = torch.zeros(B, n_vox + 1, dtype=dtype, device=xyz_ref.device)
    occ.scatter_(1, flat, 1.0)
    return occ[:, :n_vox].reshape(B, 1, grid.Z, grid.Y, grid.X)  # B×1×Z×Y×X
