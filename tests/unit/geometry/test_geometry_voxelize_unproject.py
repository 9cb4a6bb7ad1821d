"""voxelize and unproject_image against slow per-point / per-voxel loops."""

import math

import torch

from core.geometry import camera, se3
from core.geometry.grid import GridConfig
from core.geometry.unproject import unproject_image
from core.geometry.voxelize import voxelize

D = torch.float64
GRID = GridConfig(xmin=-2.0, xmax=3.0, ymin=-1.0, ymax=1.0, zmin=0.5, zmax=4.5, Z=4, Y=2, X=5)


def _slow_voxelize(xyz: torch.Tensor, valid: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    occ = torch.zeros(grid.Z, grid.Y, grid.X, dtype=D)
    v = grid.voxel_size
    for p, ok in zip(xyz.tolist(), valid.tolist()):
        if not ok or any(math.isnan(c) for c in p):
            continue
        # voxel i covers [min + i·v, min + (i+1)·v)
        i = math.floor((p[0] - grid.xmin) / v)
        j = math.floor((p[1] - grid.ymin) / v)
        k = math.floor((p[2] - grid.zmin) / v)
        if 0 <= i < grid.X and 0 <= j < grid.Y and 0 <= k < grid.Z:
            occ[k, j, i] = 1.0
    return occ


def test_voxelize_matches_slow_loop(device):
    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(2, 60, 3, generator=g, dtype=D) * torch.tensor([7.0, 3.0, 6.0], dtype=D) - torch.tensor([3.0, 1.5, 0.5], dtype=D)
    valid = torch.rand(2, 60, generator=g) > 0.2
    xyz[0, 0] = float("nan")
    occ = voxelize(xyz.to(device), GRID, valid.to(device)).cpu()
    assert occ.shape == (2, 1, 4, 2, 5)
    for b in range(2):
        assert torch.equal(occ[b, 0], _slow_voxelize(xyz[b], valid[b], GRID))
    assert voxelize(xyz, GRID).sum() >= occ.sum()


def _slow_bilinear_clamped(img: torch.Tensor, u: float, v: float) -> torch.Tensor:
    C, H, W = img.shape
    u, v = min(max(u, 0.0), W - 1.0), min(max(v, 0.0), H - 1.0)
    u0, v0 = min(math.floor(u), W - 2) if W > 1 else 0, min(math.floor(v), H - 2) if H > 1 else 0
    out = torch.zeros(C, dtype=img.dtype)
    for dv in (0, 1):
        for du in (0, 1):
            ui, vi = u0 + du, v0 + dv
            if ui < W and vi < H:
                out += max(0.0, 1 - abs(u - ui)) * max(0.0, 1 - abs(v - vi)) * img[:, vi, ui]
    return out


def test_unproject_image_matches_slow_loop(device):
    g = torch.Generator().manual_seed(1)
    B, C, H, W = 2, 3, 5, 7
    img = torch.randn(B, C, H, W, generator=g, dtype=D)
    K = camera.intrinsics(torch.tensor([4.0, 6.0], dtype=D), torch.tensor([4.0, 5.0], dtype=D), 3.0, 2.0)
    cam_T_ref = se3.random_rigid(B, 0.3, 0.5, g, dtype=D)
    vol = unproject_image(img.to(device), K.to(device), cam_T_ref.to(device), GRID).cpu()
    assert vol.shape == (B, C, GRID.Z, GRID.Y, GRID.X)
    v = GRID.voxel_size
    n_inside = 0
    for b in range(B):
        R, t = cam_T_ref[b, :3, :3], cam_T_ref[b, :3, 3]
        fx, fy, cx, cy = K[b, 0, 0].item(), K[b, 1, 1].item(), K[b, 0, 2].item(), K[b, 1, 2].item()
        for k in range(GRID.Z):
            for j in range(GRID.Y):
                for i in range(GRID.X):
                    ref = torch.tensor([GRID.xmin + (i + 0.5) * v, GRID.ymin + (j + 0.5) * v, GRID.zmin + (k + 0.5) * v], dtype=D)
                    x, y, z = (R @ ref + t).tolist()
                    expected = torch.zeros(C, dtype=D)
                    if z > 1e-6:
                        u, vv = fx * x / z + cx, fy * y / z + cy
                        if -0.5 <= u <= W - 0.5 and -0.5 <= vv <= H - 0.5:
                            expected = _slow_bilinear_clamped(img[b], u, vv)
                            n_inside += 1
                    assert torch.allclose(vol[b, :, k, j, i], expected, atol=1e-10)
    assert 0 < n_inside < B * GRID.Z * GRID.Y * GRID.X  # the test sees both cases


def test_unproject_image_pixel_centre_exact():
    # a camera at the ref origin looking down +z: the voxel centre straight ahead on the optical axis
    # projects to (cx, cy) = an integer pixel centre and must read exactly that pixel.
    grid = GridConfig(xmin=-0.5, xmax=0.5, ymin=-0.5, ymax=0.5, zmin=1.0, zmax=2.0, Z=1, Y=1, X=1)
    img = torch.arange(12, dtype=D).reshape(1, 1, 3, 4)
    K = camera.intrinsics(10.0, 10.0, 2.0, 1.0, dtype=D)
    vol = unproject_image(img, K, torch.eye(4, dtype=D)[None], grid)
    assert vol.item() == img[0, 0, 1, 2].item()


def test_unproject_image_gradcheck():
    g = torch.Generator().manual_seed(2)
    grid = GridConfig(xmin=-1.0, xmax=1.0, ymin=-0.5, ymax=0.5, zmin=1.0, zmax=3.0, Z=2, Y=1, X=2)
    img = torch.randn(1, 1, 3, 4, generator=g, dtype=D, requires_grad=True)
    K = camera.intrinsics(2.0, 2.0, 1.5, 1.0, dtype=D)
    pose = se3.random_rigid(1, 0.1, 0.1, g, dtype=D)
    assert torch.autograd.gradcheck(lambda im: unproject_image(im, K, pose, grid), (img,))
