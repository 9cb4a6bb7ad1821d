"""2D -> 3D: fill the map grid with image values by sampling the image at projected voxel centres.

Conventions (docs/conventions.md#cameras-and-pixels): images B×C×H×W; `pix` integer (u, v) are pixel centres,
so the image covers u in [−0.5, W−0.5], v in [−0.5, H−0.5]; `cam` is OpenCV (X right, Y down, Z forward);
`pix_T_cam` is 4×4 (fx=[0,0], fy=[1,1], cx=[0,2], cy=[1,2]); poses `a_T_b` with p_a = a_T_b @ p_b; volumes
B×C×Z×Y×X; integer `mem` are voxel centres.

Sampling: bilinear with `grid_sample(..., align_corners=True)` and u_norm = 2u/(W−1) − 1 (pixel centres
exact). Voxel centres whose projection falls on the image footprint but beyond the outermost pixel centres
read the edge pixels (border clamp); centres behind the camera (z <= MIN_DEPTH) or off the footprint get 0.
Differentiable w.r.t. the image.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.errors import ShapeError, check_shape
from core.geometry import camera, se3
from core.geometry.grid import GridConfig, voxel_centers_ref
from core.precision import full_precision


@full_precision  # under autocast: float32 image and pixel coordinates
def sample_image(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an image at pixel coordinates, edge-clamped.

    image: B×C×H×W, uv: B×N×2 (u, v) -> B×C×N.
    """
    B, C, H, W = image.shape
    check_shape("uv", uv, (B, None, 2))
    size = torch.tensor([max(W - 1, 1), max(H - 1, 1)], dtype=image.dtype, device=image.device)
    norm = 2.0 * uv.to(image.dtype) / size - 1.0  # B×N×2
    out = F.grid_sample(image, norm.unsqueeze(1), mode="bilinear", padding_mode="border", align_corners=True)  # B×C×1×N
    return out.squeeze(2)  # B×C×N


def in_image(uv: torch.Tensor, z: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """B×N bool: in front of the camera and on the image footprint [−0.5, W−0.5]×[−0.5, H−0.5]."""
    u, v = uv[..., 0], uv[..., 1]
    return (z > camera.MIN_DEPTH) & (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)


def unproject_image(image: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                    grid: GridConfig) -> torch.Tensor:
    """Unproject an image into the grid (every voxel along a pixel's ray gets that pixel's value).

    image: B×C×H×W, pix_T_cam: B×4×4, cam_T_ref: B×4×4, grid -> B×C×Z×Y×X
    (0 where the voxel centre is behind the camera or projects off the image).
    """
    if image.dim() != 4:
        raise ShapeError(f"image: expected B×C×H×W, got {'×'.join(map(str, image.shape))}")
    B, C, H, W = image.shape
    check_shape("pix_T_cam", pix_T_cam, (B, 4, 4))
    check_shape("cam_T_ref", cam_T_ref, (B, 4, 4))
    dtype, device = image.dtype, image.device
    xyz_ref = voxel_centers_ref(grid, dtype=dtype, device=device).expand(B, -1, 3)  # B×ZYX×3
    xyz_cam = se3.apply(cam_T_ref.to(dtype), xyz_ref)  # B×ZYX×3
    uv, z = camera.project(pix_T_cam.to(dtype), xyz_cam)  # B×ZYX×2, B×ZYX
    values = sample_image(image, uv) * in_image(uv, z, H, W).unsqueeze(1).to(dtype)  # B×C×ZYX
    return values.reshape(B, C, grid.Z, grid.Y, grid.X)  # B×C×Z×Y×X
