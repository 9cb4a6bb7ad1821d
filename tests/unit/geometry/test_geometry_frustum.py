"""frustum_resample against a per-pixel, per-plane loop; depth planes are log-spaced."""

import math

import torch

from core.geometry import camera, se3
from core.geometry.frustum import depth_planes, frustum_resample
from core.geometry.grid import GridConfig

D = torch.float64
GRID = GridConfig(xmin=-2.0, xmax=2.0, ymin=-1.0, ymax=1.0, zmin=0.0, zmax=4.0, Z=4, Y=2, X=4)


def _slow_trilinear(vol: torch.Tensor, x: float, y: float, z: float) -> torch.Tensor:
    C, Zs, Ys, Xs = vol.shape
    x0, y0, z0 = math.floor(x), math.floor(y), math.floor(z)
    out = torch.zeros(C, dtype=vol.dtype)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                xi, yi, zi = x0 + dx, y0 + dy, z0 + dz
                if 0 <= xi < Xs and 0 <= yi < Ys and 0 <= zi < Zs:
                    out += (1 - abs(x - xi)) * (1 - abs(y - yi)) * (1 - abs(z - zi)) * vol[:, zi, yi, xi]
    return out


def test_depth_planes_log_spaced():
    d = depth_planes(5, 0.5, 8.0, dtype=D)
    assert torch.allclose(d, torch.tensor([0.5, 1.0, 2.0, 4.0, 8.0], dtype=D))
    assert depth_planes(1, 2.0, 3.0).tolist() == [2.0]


def test_frustum_resample_matches_per_pixel_loop(device):
    g = torch.Generator().manual_seed(0)
    B, C, H, W, Dp = 2, 2, 3, 4, 3
    vol = torch.randn(B, C, *GRID.shape_zyx, generator=g, dtype=D)
    K = camera.intrinsics(torch.tensor([3.0, 2.0], dtype=D), torch.tensor([3.0, 2.5], dtype=D), 1.5, 1.0)
    cam_T_ref = se3.random_rigid(B, 0.2, 0.3, g, dtype=D)
    out = frustum_resample(vol.to(device), K.to(device), cam_T_ref.to(device), GRID, H, W, Dp, 0.7, 3.5).cpu()
    assert out.shape == (B, C, Dp, H, W)
    planes = [0.7 * (3.5 / 0.7) ** (i / (Dp - 1)) for i in range(Dp)]
    ref_T_cam = torch.linalg.inv(cam_T_ref)
    nonzero = 0
    for b in range(B):
        fx, fy, cx, cy = K[b, 0, 0].item(), K[b, 1, 1].item(), K[b, 0, 2].item(), K[b, 1, 2].item()
        for di, d in enumerate(planes):
            for v in range(H):
                for u in range(W):
                    cam = torch.tensor([(u - cx) / fx * d, (v - cy) / fy * d, d, 1.0], dtype=D)
                    ref = (ref_T_cam[b] @ cam)[:3]
                    mem = (ref - torch.tensor(GRID.bounds_min, dtype=D)) / GRID.voxel_size - 0.5
                    expected = _slow_trilinear(vol[b], *mem.tolist())
                    nonzero += int(expected.abs().sum() > 0)
                    assert torch.allclose(out[b, :, di, v, u], expected, atol=1e-10)
    assert nonzero > 0


def test_frustum_resample_gradcheck():
    g = torch.Generator().manual_seed(1)
    grid = GridConfig(xmin=-1.0, xmax=1.0, ymin=-1.0, ymax=1.0, zmin=0.0, zmax=2.0, Z=2, Y=2, X=2)
    vol = torch.randn(1, 1, 2, 2, 2, generator=g, dtype=D, requires_grad=True)
    K = camera.intrinsics(1.0, 1.0, 0.5, 0.5, dtype=D)
    pose = se3.random_rigid(1, 0.1, 0.1, g, dtype=D)
    assert torch.autograd.gradcheck(lambda v: frustum_resample(v, K, pose, grid, 2, 2, 2, 0.5, 1.5), (vol,))
