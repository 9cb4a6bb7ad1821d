"""Point clouds to continuous (trilinearly splatted) density volumes.

Conventions (docs/conventions.md#the-map-grid): points B×N×3 in (x, y, z), metres in `ref`; volumes
B×C×Z×Y×X; mem = (ref − min)/voxel − 0.5 (integer mem = voxel centres). Each point adds its weight to
the 8 voxel centres around it with trilinear weights (the adjoint of trilinear sampling), so unlike
core.geometry.voxelize (nearest voxel, binary) the volume moves continuously when the points move by a
fraction of a voxel: a plane between two voxel layers at fraction f splats (1 − f) and f into them.
Neighbours outside the grid receive nothing (their share is dropped).
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref


def splat_points(xyz_ref: torch.Tensor, grid: GridConfig, valid: torch.Tensor | None = None,
                 weights: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over points of weight × trilinear kernel at every voxel centre.

    xyz_ref: B×N×3 metres; valid: B×N bool or None; weights: B×N or None (1) -> B×1×Z×Y×X (dtype of xyz).
    Differentiable w.r.t. the weights and (piecewise) the points.
    """
    check_shape("xyz_ref", xyz_ref, (None, None, 3))
    B, N = xyz_ref.shape[:2]
    dtype, device = xyz_ref.dtype, xyz_ref.device
    w = torch.ones(B, N, dtype=dtype, device=device) if weights is None else weights.to(dtype)
    check_shape("weights", w, (B, N))
    if valid is not None:
        check_shape("valid", valid, (B, N))
        w = torch.where(valid.bool(), w, torch.zeros_like(w))
    mem = se3.apply(mem_T_ref(grid, dtype=dtype, device=device).expand(B, 4, 4), xyz_ref)  # B×N×3
    finite = torch.isfinite(mem).all(-1)
    w = torch.where(finite, w, torch.zeros_like(w))
    mem = torch.where(finite.unsqueeze(-1), mem, torch.zeros_like(mem))
    base = torch.floor(mem)  # B×N×3
    frac = mem - base  # B×N×3 in [0, 1)
    size = torch.tensor([grid.X, grid.Y, grid.Z], dtype=dtype, device=device)
    n_vox = grid.Z * grid.Y * grid.X
    out = torch.zeros(B, n_vox + 1, dtype=dtype, device=device)
    for ox in (0, 1):
        for oy in (0, 1):
            for oz in (0, 1):
                off = torch.tensor([ox, oy, oz], dtype=dtype, device=device)
                ijk = base + off  # B×N×3
                kern = torch.where(off.bool(), frac, 1.0 - frac).prod(-1)  # B×N
                inside = ((ijk >= 0) & (ijk < size)).all(-1)
                ijk = torch.where(inside.unsqueeze(-1), ijk, torch.zeros_like(ijk)).long()
                flat = (ijk[..., 2] * grid.Y + ijk[..., 1]) * grid.X + ijk[..., 0]
                flat = torch.where(inside, flat, torch.full_like(flat, n_vox))  # outside: the spare slot
                out = out.scatter_add(1, flat, w * kern)
    return out[:, :n_vox].reshape(B, 1, grid.Z, grid.Y, grid.X)


def surface_splat(xyz_cam: torch.Tensor, valid: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                  grid: GridConfig) -> torch.Tensor:
    """One depth image's points as the surface area they sample per voxel face, splatted trilinearly.

    xyz_cam: B×N×3 (core.geometry.camera.depth_to_points), valid: B×N, pix_T_cam, cam_T_ref: B×4×4
    -> B×1×Z×Y×X. Each point weighs its pixel's footprint at its depth, z²/(fx·fy), over the voxel face
    voxel²: a surface facing the camera and sampled densely adds ≈ 1 per voxel-face column, spread over
    the two voxel layers it passes between by its sub-voxel position (so the volume follows sub-voxel
    motion, unlike binary occupancy), and the same ≈ 1 whatever its distance to the camera (point
    density falls as 1/z²; unweighted counts would make the map's appearance depend on where the camera
    stands, which biases any alignment of two frames toward no motion).
    """
    check_shape("pix_T_cam", pix_T_cam, (xyz_cam.shape[0], 4, 4))
    f2 = (pix_T_cam[:, 0, 0] * pix_T_cam[:, 1, 1]).unsqueeze(1)  # B×1
    w = xyz_cam[..., 2].square() / f2 / grid.voxel_size ** 2  # B×N
    xyz_ref = se3.apply(se3.invert(cam_T_ref), xyz_cam)  # B×N×3
    return splat_points(xyz_ref, grid, valid, w)
