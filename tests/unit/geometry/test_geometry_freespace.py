"""free_space against a slow per-ray Amanatides–Woo voxel walk."""

import math

import torch

from core.geometry import se3
from core.geometry.freespace import free_space
from core.geometry.grid import GridConfig

D = torch.float64
GRID = GridConfig(xmin=-3.0, xmax=4.0, ymin=-2.0, ymax=2.0, zmin=0.0, zmax=6.0, Z=6, Y=4, X=7)


def _slow_walk(o: list[float], e: list[float]) -> list[tuple[int, int, int]]:
    """Voxels (x, y, z) of the infinite lattice (voxel k spans [k−0.5, k+0.5)) visited from o to e,
    in order, excluding e's voxel (Amanatides & Woo 1987)."""
    cur = [math.floor(c + 0.5) for c in o]
    last = [math.floor(c + 0.5) for c in e]
    d = [b - a for a, b in zip(o, e)]
    step = [1 if di > 0 else -1 for di in d]
    t_max = [((cur[a] + 0.5 * step[a]) - o[a]) / d[a] if d[a] != 0 else math.inf for a in range(3)]
    t_delta = [abs(1.0 / d[a]) if d[a] != 0 else math.inf for a in range(3)]
    visited = []
    for _ in range(1000):
        if cur == last:
            break
        visited.append(tuple(cur))
        a = min(range(3), key=lambda k: t_max[k])
        if t_max[a] > 1.0:
            break  # rounding: e's voxel not reached exactly
        cur[a] += step[a]
        t_max[a] += t_delta[a]
    return visited


def _slow_free_space(xyz_cam, valid, cam_T_ref, grid):
    B, N = xyz_cam.shape[:2]
    free = torch.zeros(B, 1, grid.Z, grid.Y, grid.X, dtype=D)
    for b in range(B):
        ref_T_cam = torch.linalg.inv(cam_T_ref[b])
        to_mem = lambda p: ((ref_T_cam[:3, :3] @ p + ref_T_cam[:3, 3]) - torch.tensor(grid.bounds_min, dtype=D)) / grid.voxel_size - 0.5
        o = to_mem(torch.zeros(3, dtype=D)).tolist()
        for n in range(N):
            if not valid[b, n]:
                continue
            for x, y, z in _slow_walk(o, to_mem(xyz_cam[b, n]).tolist()):
                if 0 <= x < grid.X and 0 <= y < grid.Y and 0 <= z < grid.Z:
                    free[b, 0, z, y, x] = 1.0
    return free


def test_free_space_matches_slow_ray_walk(device):
    g = torch.Generator().manual_seed(0)
    B, N = 2, 40
    cam_T_ref = se3.random_rigid(B, 0.3, 1.0, g, dtype=D)
    # camera at the grid's near edge (ref origin) looking into it; points scattered in and beyond it
    xyz = torch.rand(B, N, 3, generator=g, dtype=D) * torch.tensor([9.0, 5.0, 8.0], dtype=D) - torch.tensor([4.0, 2.5, -0.5], dtype=D)
    valid = torch.rand(B, N, generator=g) > 0.1
    got = free_space(xyz.to(device), valid.to(device), cam_T_ref.to(device), GRID).cpu()
    expected = _slow_free_space(xyz, valid, cam_T_ref, GRID)
    assert expected.sum() > 20
    assert torch.equal(got, expected)


def test_free_space_excludes_point_voxel_and_camera_outside_grid():
    grid = GridConfig(xmin=-0.5, xmax=0.5, ymin=-0.5, ymax=0.5, zmin=2.0, zmax=7.0, Z=5, Y=1, X=1)
    # camera 2 m in front of the grid, point in the 4th voxel along the optical axis
    xyz = torch.tensor([[[0.0, 0.0, 5.5]]], dtype=D)
    free = free_space(xyz, None, torch.eye(4, dtype=D)[None], grid)
    assert free[0, 0, :, 0, 0].tolist() == [1.0, 1.0, 1.0, 0.0, 0.0]


def test_free_space_chunking_is_invisible(monkeypatch):
    import core.geometry.freespace as fs
    g = torch.Generator().manual_seed(1)
    xyz = torch.rand(1, 30, 3, generator=g) * torch.tensor([6.0, 3.0, 6.0]) - torch.tensor([3.0, 1.5, 0.0])
    pose = torch.eye(4)[None]
    whole = free_space(xyz, None, pose, GRID)
    monkeypatch.setattr(fs, "_CHUNK_ELEMENTS", 50)
    assert torch.equal(free_space(xyz, None, pose, GRID), whole)


def test_axis_parallel_rays_and_a_camera_outside_the_grid_match_the_slow_walk():
    """Rays with a zero component (parallel to a plane family, off the planes) and a camera behind the grid,
    so every ray enters through a face: the walk's box clipping and entry voxel against the per-ray walk."""
    g = torch.Generator().manual_seed(2)
    N = 60
    cam_T_ref = se3.from_rt(torch.eye(3, dtype=D)[None], torch.tensor([[0.3, -0.2, 2.0]], dtype=D))  # camera 2 m behind
    xyz = torch.rand(1, N, 3, generator=g, dtype=D) * torch.tensor([9.0, 5.0, 9.0], dtype=D) - torch.tensor([4.5, 2.5, 0.0], dtype=D)
    xyz[0, :20, 0] = 0.0   # x = 0 in the camera: no x motion
    xyz[0, 20:40, 1] = 0.0  # y = 0: no y motion
    got = free_space(xyz, None, cam_T_ref, GRID)
    expected = _slow_free_space(xyz, torch.ones(1, N, dtype=torch.bool), cam_T_ref, GRID)
    assert expected.sum() > 20
    assert torch.equal(got, expected)
