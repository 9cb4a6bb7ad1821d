"""3D -> 2D: resample the map volume into a camera's frustum (pixel rays × log-spaced depth planes).

Conventions (docs/conventions.md#cameras-and-pixels): `pix` integer (u, v) are pixel centres; `cam` OpenCV (X
right, Y down, Z forward, metres); `pix_T_cam` is 4×4 (fx=[0,0], fy=[1,1], cx=[0,2], cy=[1,2]); poses `a_T_b`
with p_a = a_T_b @ p_b; volumes B×C×Z×Y×X with integer `mem` at voxel centres; depth is metres along Z.

For output pixel (u, v) (u = 0..W−1, v = 0..H−1, so `pix_T_cam` must be the intrinsics of the H×W output
image — see `camera.scale_intrinsics`) and plane d, the sample point is unproject(u, v, d) in cam, mapped
to ref by invert(cam_T_ref), then to mem, and read trilinearly (align_corners=True, zeros outside the grid).
Differentiable w.r.t. the volume.
"""

from __future__ import annotations

import math

import torch

from core.errors import check_shape
from core.geometry import camera, se3
from core.geometry.grid import GridConfig, mem_T_ref
from core.geometry.resample import check_volume_matches_grid, sample_volume_at


def depth_planes(D: int, dmin: float, dmax: float, *, dtype: torch.dtype = torch.float32,
                 device: torch.device | str | None = None) -> torch.Tensor:
    """D depths (metres) log-spaced from dmin to dmax inclusive (D = 1 gives [dmin])."""
    if D < 1 or not (0 < dmin <= dmax):
        raise ValueError(f"depth_planes needs D >= 1 and 0 < dmin <= dmax, got D={D} dmin={dmin} dmax={dmax}")
    return torch.exp(torch.linspace(math.log(dmin), math.log(dmax), D, dtype=dtype, device=device))


def frustum_points_cam(pix_T_cam: torch.Tensor, H: int, W: int, depths: torch.Tensor) -> torch.Tensor:
    """Camera points of every pixel centre at every depth plane.

    pix_T_cam: B×4×4, depths: D -> B×(D·H·W)×3 ordered (d, v, u), u fastest.
    """
    B, D = pix_T_cam.shape[0], depths.shape[0]
    uv = camera.pixel_grid(H, W, dtype=pix_T_cam.dtype, device=pix_T_cam.device)  # HW×2
    uv = uv.unsqueeze(0).expand(D, H * W, 2).reshape(1, D * H * W, 2).expand(B, -1, 2)  # B×DHW×2
    z = depths.to(pix_T_cam.dtype).reshape(D, 1).expand(D, H * W).reshape(1, D * H * W).expand(B, -1)  # B×DHW
    return camera.unproject(pix_T_cam, uv, z)


def frustum_resample(vol_ref: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor, grid: GridConfig,
                     H: int, W: int, D: int, dmin: float, dmax: float) -> torch.Tensor:
    """One trilinear sampling of the ref volume along every pixel ray at D log-spaced depths.

    vol_ref: B×C×Z×Y×X (on `grid`), pix_T_cam: B×4×4 (for an H×W image), cam_T_ref: B×4×4
    -> B×C×D×H×W, plane index 0 = dmin.
    """
    check_volume_matches_grid("vol_ref", vol_ref, grid)
    B = vol_ref.shape[0]
    check_shape("pix_T_cam", pix_T_cam, (B, 4, 4))
    check_shape("cam_T_ref", cam_T_ref, (B, 4, 4))
    dtype, device = vol_ref.dtype, vol_ref.device
    depths = depth_planes(D, dmin, dmax, dtype=dtype, device=device)
    xyz_cam = frustum_points_cam(pix_T_cam.to(dtype), H, W, depths)  # B×DHW×3
    mem_T_cam = se3.compose(mem_T_ref(grid, dtype=dtype, device=device).expand(B, 4, 4),
                            se3.invert(cam_T_ref.to(dtype)))  # B×4×4
    xyz_mem = se3.apply(mem_T_cam, xyz_cam).reshape(B, D, H, W, 3)  # B×D×H×W×3
    return sample_volume_at(vol_ref, xyz_mem)  # B×C×D×H×W
