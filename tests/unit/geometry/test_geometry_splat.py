"""Trilinear point splatting (core.geometry.splat) against a per-point loop, and its sub-voxel behaviour."""

import itertools
import math

import torch

from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref
from core.geometry.splat import splat_points, surface_splat

GRID = GridConfig(xmin=-2, xmax=2, ymin=-1, ymax=1, zmin=-2, zmax=2, Z=4, Y=2, X=4)  # 1 m voxels


def _slow_splat(xyz: torch.Tensor, w: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """One point, one neighbour at a time: N×3 metres, N weights -> Z×Y×X."""
    out = torch.zeros(grid.Z, grid.Y, grid.X, dtype=torch.float64)
    m = mem_T_ref(grid, dtype=torch.float64)
    for p, wi in zip(xyz.double(), w.double()):
        mem = (m[:3, :3] @ p + m[:3, 3]).tolist()
        for corner in itertools.product((0, 1), repeat=3):
            idx = [math.floor(c) + o for c, o in zip(mem, corner)]
            kern = 1.0
            for c, i in zip(mem, idx):
                kern *= 1.0 - abs(c - i)
            x, y, z = idx
            if 0 <= x < grid.X and 0 <= y < grid.Y and 0 <= z < grid.Z:
                out[z, y, x] += float(wi) * kern
    return out


def test_splat_matches_the_loop_reference_and_drops_invalid_points():
    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(1, 30, 3, generator=g) * 2 - 1) * torch.tensor([2.6, 1.4, 2.6])  # some fall outside
    w = torch.rand(1, 30, generator=g)
    valid = torch.rand(1, 30, generator=g) > 0.2
    fast = splat_points(xyz, GRID, valid, w)[0, 0]
    slow = _slow_splat(xyz[0][valid[0]], w[0][valid[0]], GRID)
    torch.testing.assert_close(fast.double(), slow, atol=1e-5, rtol=1e-5)


def test_splat_follows_sub_voxel_motion_and_keeps_mass_and_centroid():
    # one point between voxel centres: its mass is conserved and its splat's centroid is the point itself,
    # so moving the point by 0.3 voxel moves the centroid by 0.3 voxel (binary occupancy would not move)
    for shift in (0.0, 0.3):
        p = torch.tensor([[[0.2 + shift, -0.1, 0.35]]])
        vol = splat_points(p, GRID)[0, 0]  # Z×Y×X
        assert float(vol.sum()) == torch.tensor(1.0).item()
        z, y, x = torch.meshgrid(*(torch.arange(n, dtype=torch.float32) for n in GRID.shape_zyx), indexing="ij")
        centroid_mem = torch.stack([(vol * x).sum(), (vol * y).sum(), (vol * z).sum()])
        expected = (mem_T_ref(GRID)[:3, :3] @ p[0, 0] + mem_T_ref(GRID)[:3, 3])
        torch.testing.assert_close(centroid_mem, expected, atol=1e-5, rtol=0)


def test_surface_splat_weighs_points_by_their_pixel_footprint():
    # a point at depth z seen with focal lengths fx, fy samples z²/(fx·fy) m² of surface; on 1 m voxels
    # that is its whole splat mass
    pix_T_cam = torch.eye(4)[None]
    pix_T_cam[0, 0, 0], pix_T_cam[0, 1, 1] = 2.0, 4.0
    xyz_cam = torch.tensor([[[0.1, 0.2, 1.5], [0.0, 0.0, 0.9]]])
    valid = torch.tensor([[True, False]])
    vol = surface_splat(xyz_cam, valid, pix_T_cam, torch.eye(4)[None], GRID)
    assert abs(float(vol.sum()) - 1.5 ** 2 / 8.0) < 1e-6
    # and it lands where cam_T_ref says: a camera 0.5 m along +x of ref sees the point at ref x = 0.6
    cam_T_ref = se3.invert(se3.from_rt(torch.eye(3)[None], torch.tensor([[0.5, 0.0, 0.0]])))
    moved = surface_splat(xyz_cam, valid, pix_T_cam, cam_T_ref, GRID)
    ref_pt = torch.tensor([[[0.6, 0.2, 1.5]]])
    torch.testing.assert_close(moved, splat_points(ref_pt, GRID, weights=torch.full((1, 1), 1.5 ** 2 / 8.0)))
