"""2D->3D input of the mapper: one RGB-D view lifted into the map grid of `ref` (paper appendix).

Channels are [occupancy, R−0.5, G−0.5, B−0.5] (docs/conventions.md#tensor-layouts):
- RGB: bilinear sample of the image at each voxel centre's projection (core.geometry.unproject_image),
  centred so voxels outside the view hold 0 (mid grey) rather than black;
- occupancy (`occupancy="binary"`, the default): the view's depth points voxelised in `ref` (1 where a
  point lands, at the nearest voxel centre);
- or (`occupancy="splat"`) a continuous occupancy in [0, 1]: the surface area the points sample per voxel
  face, splatted trilinearly (core.geometry.splat.surface_splat), clamped to 1. It moves continuously when
  the camera moves by a fraction of a voxel, which binary occupancy does not: on the small preset's
  moving-camera test pairs, dense alignment of two binary volumes of the SAME points moved by the true
  motion ends 0.0034 rad / 0.061 m off (the quantisation floor), of the splatted ones 0.0005 rad /
  0.006 m (tests/benchmarks/bench_egomotion_precision.py --floors). The egomotion module's sub-voxel
  stage reads it.
Registration with known poses happens here: the caller passes cam_T_ref = inv(world_T_cam)·world_T_ref,
so every view is unprojected straight into `ref` (no second interpolation by warping).
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.camera import depth_to_points
from core.geometry.grid import GridConfig
from core.geometry.splat import surface_splat
from core.geometry.unproject import unproject_image
from core.geometry.voxelize import voxelize

OCCUPANCY_KINDS = ("binary", "splat")


def input_volume(rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                 cam_T_ref: torch.Tensor, grid: GridConfig, *,
                 occupancy: str = "binary") -> tuple[torch.Tensor, torch.Tensor]:
    """Lift one view per batch element into the grid (`occupancy`: "binary" or "splat", see the module doc).

    rgb: B×3×H×W in [0, 1]; depth: B×H×W metres (0 = missing); pix_T_cam, cam_T_ref: B×4×4.
    Returns (volume B×4×Z×Y×X = [occupancy, rgb−0.5], in_view B×1×Z×Y×X in {0, 1}: voxel centres
    that project inside the image in front of the camera).
    """
    B, _, H, W = rgb.shape
    check_shape("rgb", rgb, (B, 3, H, W))
    check_shape("depth", depth, (B, H, W))
    # One unprojection for colour and a ones-channel: the latter is 1 exactly where a voxel sees the image.
    lifted = unproject_image(torch.cat([rgb - 0.5, torch.ones_like(rgb[:, :1])], dim=1),
                             pix_T_cam, cam_T_ref, grid)  # B×4×Z×Y×X
    rgb_vol, coverage = lifted[:, :3], lifted[:, 3:]
    xyz_cam, valid = depth_to_points(depth, pix_T_cam)  # B×(H·W)×3, B×(H·W)
    xyz_ref = se3.apply(se3.invert(cam_T_ref), xyz_cam)  # B×(H·W)×3
    if occupancy == "binary":
        occ = voxelize(xyz_ref, grid, valid).to(rgb.dtype)  # B×1×Z×Y×X
    elif occupancy == "splat":
        occ = surface_splat(xyz_cam, valid, pix_T_cam, cam_T_ref, grid).clamp(max=1.0).to(rgb.dtype)
    else:
        raise ValueError(f"input_volume: occupancy must be one of {OCCUPANCY_KINDS}, got {occupancy!r}")
    in_view = (coverage > 0.5).to(rgb.dtype)
    return torch.cat([occ, rgb_vol], dim=1), in_view
