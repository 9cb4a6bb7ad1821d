"""Partial occupancy labels from depth (paper appendix): occupied = voxelised points, free = voxels the
camera rays cross before reaching their point. Shared by the occupancy task and its evaluation."""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.camera import depth_to_points
from core.geometry.freespace import free_space
from core.geometry.grid import GridConfig
from core.geometry.voxelize import voxelize


@torch.no_grad()
def occupancy_labels(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                     grid: GridConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """depth: B×V×H×W metres; pix_T_cam, cam_T_ref: B×V×4×4 -> (occupied, free), each B×1×Z×Y×X bool,
    the union over the V views (a voxel occupied in any view is not free)."""
    B, V, H, W = depth.shape
    check_shape("pix_T_cam", pix_T_cam, (B, V, 4, 4))
    check_shape("cam_T_ref", cam_T_ref, (B, V, 4, 4))
    xyz_cam, valid = depth_to_points(depth.reshape(B * V, H, W), pix_T_cam.reshape(B * V, 4, 4))  # (B·V)×N×3
    cam = cam_T_ref.reshape(B * V, 4, 4)
    xyz_ref = se3.apply(se3.invert(cam), xyz_cam)  # (B·V)×N×3
    occ = voxelize(xyz_ref, grid, valid).reshape(B, V, 1, *grid.shape_zyx) > 0.5  # B×V×1×Z×Y×X
    free = free_space(xyz_cam, valid, cam, grid).reshape(B, V, 1, *grid.shape_zyx) > 0.5  # B×V×1×Z×Y×X
    occupied = occ.any(dim=1)
    return occupied, free.any(dim=1) & ~occupied
