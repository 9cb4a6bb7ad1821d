"""Pinhole cameras: intrinsics as 4×4 `pix_T_cam`, projection, unprojection, depth <-> points.

Conventions (docs/conventions.md#cameras-and-pixels):
- `pix`: u right, v down; integer (u, v) are pixel CENTRES, so pixel (i, j) covers u in [i-0.5, i+0.5].
  An H×W image spans u in [-0.5, W-0.5], v in [-0.5, H-0.5]; its centre is ((W-1)/2, (H-1)/2).
- `cam`: OpenCV camera, X right, Y down, Z forward, metres. Depth is metres along Z, 0 = missing.
- `pix_T_cam` is 4×4: fx = [0,0], fy = [1,1], cx = [0,2], cy = [1,2], [2,2] = [3,3] = 1:
      u = fx·x/z + cx,  v = fy·y/z + cy.
- Poses are `a_T_b` with p_a = a_T_b @ p_b. Point sets B×N×3 in (x, y, z); images B×C×H×W.
Device and dtype follow the inputs.
"""

from __future__ import annotations

import math

import torch

from core.errors import ShapeError, check_shape

# Points with z at or below this (metres) are "behind the camera" for projection purposes.
MIN_DEPTH = 1e-6


def _as_batch(value, *, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=dtype, device=device)
    return t.reshape(1) if t.dim() == 0 else t


def intrinsics(fx, fy, cx, cy, *, dtype: torch.dtype | None = None,
               device: torch.device | str | None = None) -> torch.Tensor:
    """B×4×4 `pix_T_cam` from B-vectors (or Python floats, giving B = 1) of fx, fy, cx, cy (pixels)."""
    ref = next((v for v in (fx, fy, cx, cy) if isinstance(v, torch.Tensor)), None)
    dtype = dtype or (ref.dtype if ref is not None and ref.is_floating_point() else torch.float32)
    device = device or (ref.device if ref is not None else None)
    fx, fy, cx, cy = torch.broadcast_tensors(*(_as_batch(v, dtype=dtype, device=device) for v in (fx, fy, cx, cy)))
    K = torch.zeros(*fx.shape, 4, 4, dtype=dtype, device=device)
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2] = fx, fy, cx, cy
    K[..., 2, 2] = 1.0
    K[..., 3, 3] = 1.0
    return K


def intrinsics_from_fov(H: int, W: int, hfov_deg, *, dtype: torch.dtype = torch.float32,
                        device: torch.device | str | None = None) -> torch.Tensor:
    """B×4×4 `pix_T_cam` for an H×W image with horizontal field of view `hfov_deg` (float -> B = 1,
    or a B-vector), square pixels and the principal point at the image centre ((W-1)/2, (H-1)/2).

    The field of view spans the full image width W (pixel edges at -0.5 and W-0.5).
    """
    hfov = _as_batch(hfov_deg, dtype=dtype, device=device)
    if not bool(((hfov > 0) & (hfov < 180)).all()):
        raise ValueError(f"hfov_deg must be in (0, 180), got {hfov.tolist()}")
    f = (W / 2.0) / torch.tan(hfov * (math.pi / 360.0))
    return intrinsics(f, f, (W - 1) / 2.0, (H - 1) / 2.0, dtype=dtype, device=device)


def scale_intrinsics(pix_T_cam: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics for an image resized by (sx, sy) (new W = sx·W). ...×4×4 -> ...×4×4.

    Pixel-centre convention: u' = sx·(u + 0.5) - 0.5, so fx' = sx·fx and cx' = sx·(cx + 0.5) - 0.5.
    """
    check_shape("pix_T_cam", pix_T_cam, (*pix_T_cam.shape[:-2], 4, 4))
    K = pix_T_cam.clone()
    K[..., 0, 0] = pix_T_cam[..., 0, 0] * sx
    K[..., 1, 1] = pix_T_cam[..., 1, 1] * sy
    K[..., 0, 2] = (pix_T_cam[..., 0, 2] + 0.5) * sx - 0.5
    K[..., 1, 2] = (pix_T_cam[..., 1, 2] + 0.5) * sy - 0.5
    return K


def _fxfycxcy(pix_T_cam: torch.Tensor):
    """B×4×4 -> four B×1 tensors (ready to broadcast against B×N)."""
    if pix_T_cam.dim() != 3 or pix_T_cam.shape[-2:] != (4, 4):
        raise ShapeError(f"pix_T_cam: expected shape B×4×4, got {'×'.join(map(str, pix_T_cam.shape))}")
    return (pix_T_cam[:, 0, 0:1], pix_T_cam[:, 1, 1:2], pix_T_cam[:, 0, 2:3], pix_T_cam[:, 1, 2:3])


def project(pix_T_cam: torch.Tensor, xyz_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera points to pixels.

    pix_T_cam: B×4×4, xyz_cam: B×N×3 -> (uv: B×N×2, z: B×N).
    `uv` is only meaningful where z > 0: z is clamped to MIN_DEPTH in the division (so uv stays finite);
    callers must mask with `z > 0` themselves.
    """
    check_shape("xyz_cam", xyz_cam, (pix_T_cam.shape[0], None, 3))
    fx, fy, cx, cy = _fxfycxcy(pix_T_cam)
    x, y, z = xyz_cam.unbind(-1)
    z_safe = z.clamp_min(MIN_DEPTH)
    uv = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)  # B×N×2
    return uv, z


def unproject(pix_T_cam: torch.Tensor, uv: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Pixels at depth z (metres along Z) to camera points.

    pix_T_cam: B×4×4, uv: B×N×2, z: B×N -> xyz_cam: B×N×3.
    """
    check_shape("uv", uv, (pix_T_cam.shape[0], None, 2))
    check_shape("z", z, uv.shape[:2])
    fx, fy, cx, cy = _fxfycxcy(pix_T_cam)
    x = (uv[..., 0] - cx) / fx * z
    y = (uv[..., 1] - cy) / fy * z
    return torch.stack([x, y, z], dim=-1)  # B×N×3


def pixel_grid(H: int, W: int, *, dtype: torch.dtype = torch.float32,
               device: torch.device | str | None = None) -> torch.Tensor:
    """(H·W)×2 pixel-centre coordinates (u, v), flattened row-major (v outer, u inner)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype, device=device),
                          torch.arange(W, dtype=dtype, device=device), indexing="ij")
    return torch.stack([u, v], dim=-1).reshape(H * W, 2)  # H·W×2


def depth_to_points(depth: torch.Tensor, pix_T_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth image to a camera point cloud.

    depth: B×H×W (metres along Z, 0 = missing), pix_T_cam: B×4×4
    -> (xyz_cam: B×(H·W)×3 in row-major pixel order, valid: B×(H·W) bool = depth > 0 and finite).
    Invalid pixels keep their (meaningless) coordinates with depth replaced by 0.
    """
    if depth.dim() != 3:
        raise ShapeError(f"depth: expected shape B×H×W, got {'×'.join(map(str, depth.shape))}")
    B, H, W = depth.shape
    check_shape("pix_T_cam", pix_T_cam, (B, 4, 4))
    z = depth.reshape(B, H * W)  # B×H·W
    valid = torch.isfinite(z) & (z > 0)
    z = torch.where(valid, z, torch.zeros_like(z))
    uv = pixel_grid(H, W, dtype=depth.dtype, device=depth.device).expand(B, H * W, 2)  # B×H·W×2
    return unproject(pix_T_cam, uv, z), valid


def points_to_depth(xyz_cam: torch.Tensor, pix_T_cam: torch.Tensor, H: int, W: int,
                    valid: torch.Tensor | None = None) -> torch.Tensor:
    """Z-buffer camera points into a depth image (nearest pixel, smallest z wins, 0 = empty).

    xyz_cam: B×N×3, pix_T_cam: B×4×4, valid: B×N bool or None -> depth: B×H×W.
    Points with z <= 0, off the image, or not valid are ignored. Not differentiable (a z-buffer).
    """
    B, N = xyz_cam.shape[:2]
    uv, z = project(pix_T_cam, xyz_cam)
    ij = torch.floor(uv + 0.5).long()  # B×N×2, nearest pixel centre
    keep = (z > MIN_DEPTH) & (ij[..., 0] >= 0) & (ij[..., 0] < W) & (ij[..., 1] >= 0) & (ij[..., 1] < H)
    keep &= torch.isfinite(z)
    if valid is not None:
        check_shape("valid", valid, (B, N))
        keep &= valid.bool()
    flat = torch.where(keep, ij[..., 1] * W + ij[..., 0], torch.full_like(ij[..., 0], H * W))  # B×N
    inf = torch.full((B, H * W + 1), float("inf"), dtype=xyz_cam.dtype, device=xyz_cam.device)
    zbuf = inf.scatter_reduce(1, flat, z.detach(), reduce="amin", include_self=True)[:, : H * W]  # B×H·W
    zbuf = torch.where(torch.isinf(zbuf), torch.zeros_like(zbuf), zbuf)
    return zbuf.reshape(B, H, W)  # B×H×W
