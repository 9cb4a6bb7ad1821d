"""resample: identity warps exact, integer shifts, 90° rotations, slow trilinear reference, gradcheck."""

import math

import pytest
import torch

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import sample_volume, warp_flow, warp_rigid

D = torch.float64
GRID = GridConfig(xmin=-3.0, xmax=3.0, ymin=-1.0, ymax=1.0, zmin=-3.0, zmax=3.0, Z=6, Y=2, X=6)


def _slow_trilinear(vol: torch.Tensor, x: float, y: float, z: float) -> torch.Tensor:
    """vol: C×Z×Y×X; corners outside the volume contribute zero."""
    C, Zs, Ys, Xs = vol.shape
    x0, y0, z0 = math.floor(x), math.floor(y), math.floor(z)
    out = torch.zeros(C, dtype=vol.dtype, device=vol.device)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                xi, yi, zi = x0 + dx, y0 + dy, z0 + dz
                w = (1 - abs(x - xi)) * (1 - abs(y - yi)) * (1 - abs(z - zi))
                if 0 <= xi < Xs and 0 <= yi < Ys and 0 <= zi < Zs:
                    out += w * vol[:, zi, yi, xi]
    return out


@pytest.mark.parametrize("dtype", [torch.float32, D])
def test_identity_warps_exact(device, dtype):
    g = torch.Generator().manual_seed(0)
    vol = torch.randn(2, 3, GRID.Z, GRID.Y, GRID.X, generator=g, dtype=dtype).to(device)
    eye = torch.eye(4, dtype=dtype, device=device).expand(2, 4, 4)
    assert (warp_rigid(vol, eye, GRID) - vol).abs().max() < 1e-6
    assert (warp_flow(vol, torch.zeros(2, 3, *GRID.shape_zyx, dtype=dtype, device=device)) - vol).abs().max() < 1e-6


def test_integer_translation_shifts_by_k_voxels(device):
    vol = torch.randn(1, 2, GRID.Z, GRID.Y, GRID.X, dtype=D).to(device)
    k = (2, -1, 1)  # voxels along x, y, z
    b_T_a = torch.eye(4, dtype=D, device=device)[None].clone()
    b_T_a[0, :3, 3] = torch.tensor(k, dtype=D) * GRID.voxel_size
    out = warp_rigid(vol, b_T_a, GRID)
    flow = torch.tensor(k, dtype=D, device=device).reshape(1, 3, 1, 1, 1).expand(1, 3, *GRID.shape_zyx)
    out_flow = warp_flow(vol, flow)
    expected = torch.zeros_like(vol)
    for z in range(GRID.Z):
        for y in range(GRID.Y):
            for x in range(GRID.X):
                xs, ys, zs = x + k[0], y + k[1], z + k[2]
                if 0 <= xs < GRID.X and 0 <= ys < GRID.Y and 0 <= zs < GRID.Z:
                    expected[0, :, z, y, x] = vol[0, :, zs, ys, xs]
    assert torch.allclose(out, expected, atol=1e-9)
    assert torch.allclose(out_flow, expected, atol=1e-9)


def test_quarter_turn_about_y_permutes_voxels(device):
    vol = torch.randn(1, 1, GRID.Z, GRID.Y, GRID.X, dtype=D).to(device)
    b_T_a = se3.from_rt(se3.yaw_to_matrix(torch.tensor([math.pi / 2], dtype=D)), torch.zeros(1, 3, dtype=D)).to(device)
    out = warp_rigid(vol, b_T_a, GRID)
    # p_b = R p_a with R = yaw(90°): x_b = z_a, z_b = -x_a; the grid is centred, so in mem
    # x_b = z_a and z_b = (X-1) - x_a.
    expected = torch.empty_like(vol)
    for z in range(GRID.Z):
        for y in range(GRID.Y):
            for x in range(GRID.X):
                expected[0, 0, z, y, x] = vol[0, 0, GRID.X - 1 - x, y, z]
    assert torch.allclose(out, expected, atol=1e-9)


def test_sample_volume_matches_slow_trilinear(device):
    g = torch.Generator().manual_seed(1)
    for shape in [(4, 3, 5), (4, 1, 5)]:  # including a size-1 axis
        vol = torch.randn(2, 2, *shape, generator=g, dtype=D)
        extent = torch.tensor([shape[2], shape[1], shape[0]], dtype=D)
        pts = torch.rand(2, 40, 3, generator=g, dtype=D) * (extent + 2.0) - 1.5  # some outside
        got = sample_volume(vol.to(device), pts.to(device)).cpu()
        for b in range(2):
            for n in range(40):
                assert torch.allclose(got[b, :, n], _slow_trilinear(vol[b], *pts[b, n].tolist()), atol=1e-12)


def test_warp_rigid_matches_pointwise_definition():
    g = torch.Generator().manual_seed(2)
    vol = torch.randn(1, 1, GRID.Z, GRID.Y, GRID.X, generator=g, dtype=D)
    b_T_a = se3.random_rigid(1, 0.4, 0.8, g, dtype=D)
    out = warp_rigid(vol, b_T_a, GRID)
    v = GRID.voxel_size
    for z in range(GRID.Z):
        for y in range(GRID.Y):
            for x in range(GRID.X):
                ref_a = torch.tensor([GRID.xmin + (x + 0.5) * v, GRID.ymin + (y + 0.5) * v, GRID.zmin + (z + 0.5) * v], dtype=D)
                ref_b = b_T_a[0, :3, :3] @ ref_a + b_T_a[0, :3, 3]
                mem_b = (ref_b - torch.tensor(GRID.bounds_min, dtype=D)) / v - 0.5
                assert torch.allclose(out[0, :, z, y, x], _slow_trilinear(vol[0], *mem_b.tolist()), atol=1e-12)


def test_gradcheck_tiny_warps():
    g = torch.Generator().manual_seed(3)
    grid = GridConfig(xmin=0.0, xmax=3.0, ymin=0.0, ymax=2.0, zmin=0.0, zmax=2.0, Z=2, Y=2, X=3)
    vol = torch.randn(1, 1, 2, 2, 3, generator=g, dtype=D, requires_grad=True)
    b_T_a = se3.random_rigid(1, 0.2, 0.3, g, dtype=D)
    assert torch.autograd.gradcheck(lambda v: warp_rigid(v, b_T_a, grid), (vol,))
    # the warp is differentiable w.r.t. the pose too (egomotion backpropagates through it)
    rt = (torch.rand(1, 6, generator=g, dtype=D) * 0.2 + 0.05).requires_grad_(True)
    warp_pose = lambda p: warp_rigid(vol.detach(), se3.from_rt(se3.axis_angle_to_matrix(p[:, :3]), p[:, 3:]), grid)
    assert torch.autograd.gradcheck(warp_pose, (rt,))
    flow = (torch.rand(1, 3, 2, 2, 3, generator=g, dtype=D) * 0.8 + 0.1).requires_grad_(True)  # off integer kinks
    assert torch.autograd.gradcheck(warp_flow, (vol, flow))


def test_shape_errors_name_the_argument():
    with pytest.raises(ShapeError, match="vol_b"):
        warp_rigid(torch.zeros(1, 1, 3, 3, 3), torch.eye(4)[None], GRID)
    with pytest.raises(ShapeError, match="flow"):
        warp_flow(torch.zeros(1, 1, 3, 3, 3), torch.zeros(1, 2, 3, 3, 3))
