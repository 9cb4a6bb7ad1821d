"""core/geometry/tsdf.py against slow, obvious references: bilinear depth per point, the projective TSDF voxel by
voxel and view by view, the band's box sums against pooling, cell means against the ICP baseline's downsampling,
and a wall whose TSDF is known in closed form."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from core.baselines.icp import voxel_downsample
from core.geometry import se3
from core.geometry.camera import depth_to_points, intrinsics
from core.geometry.grid import GridConfig
from core.geometry.tsdf import _box_sum, bilinear_depth, cell_mean_points, projective_tsdf, surface_band

D = torch.float64
GRID = GridConfig(xmin=-2.0, xmax=2.0, ymin=-1.0, ymax=1.0, zmin=0.0, zmax=4.0, Z=8, Y=4, X=8)


def _slow_bilinear(depth: torch.Tensor, u: float, v: float, max_spread: float) -> float:
    H, W = depth.shape
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    if not (0 <= u0 < W - 1 and 0 <= v0 < H - 1):
        return 0.0
    c = [float(depth[v0, u0]), float(depth[v0, u0 + 1]), float(depth[v0 + 1, u0]), float(depth[v0 + 1, u0 + 1])]
    if min(c) <= 0 or max(c) - min(c) > max_spread * max(c):
        return 0.0
    fu, fv = u - u0, v - v0
    return (c[0] * (1 - fu) + c[1] * fu) * (1 - fv) + (c[2] * (1 - fu) + c[3] * fu) * fv


def test_bilinear_depth_matches_a_per_point_loop_with_its_edge_rules():
    g = torch.Generator().manual_seed(0)
    depth = 2.0 + 0.02 * torch.rand(1, 6, 7, generator=g, dtype=D)
    depth[0, 2, 3] = 0.0          # a pixel without depth
    depth[0, 4, 1] = 5.0          # a depth edge
    uv = torch.rand(1, 200, 2, generator=g, dtype=D) * torch.tensor([8.0, 7.0], dtype=D) - 0.5  # some outside
    got = bilinear_depth(depth, uv, max_spread=0.05)
    slow = torch.tensor([[_slow_bilinear(depth[0], float(u), float(v), 0.05) for u, v in uv[0]]], dtype=D)
    torch.testing.assert_close(got, slow)
    assert 0 < int((got > 0).sum()) < 200  # the rules drop some points and keep most


def test_box_sums_equal_pooling():
    x = (torch.rand(2, 1, 7, 5, 9, generator=torch.Generator().manual_seed(1)) > 0.8).float()
    for dim, kernel in ((2, (5, 1, 1)), (3, (1, 5, 1)), (4, (1, 1, 5))):
        padding = tuple(2 if k == 5 else 0 for k in kernel)
        expected = F.avg_pool3d(x, kernel, stride=1, padding=padding, count_include_pad=True) * 5
        torch.testing.assert_close(_box_sum(x, 2, dim), expected)


def _views(V: int = 2):
    """Two cameras looking along +Z from slightly different places at a bumpy wall: depth 1×V×5×6."""
    g = torch.Generator().manual_seed(2)
    pix = intrinsics(3.0, 3.0, 2.5, 2.0).to(D).expand(1, V, 4, 4).clone()
    cam_T_ref = torch.stack([se3.from_rt(se3.axis_angle_to_matrix(torch.tensor([[0.0, 0.05 * v, 0.0]], dtype=D)),
                                         torch.tensor([[0.1 * v, 0.0, 0.2]], dtype=D))[0] for v in range(V)])[None]
    depth = 2.5 + 0.3 * torch.rand(1, V, 5, 6, generator=g, dtype=D)
    depth[0, 0, 1, 1] = 0.0
    return depth, pix, cam_T_ref


def test_projective_tsdf_matches_a_voxel_by_voxel_loop_inside_its_band():
    depth, pix, cam_T_ref = _views()
    trunc = 0.75
    got = projective_tsdf(depth, pix, cam_T_ref, GRID, truncation_m=trunc, band_voxels=20)  # band: every voxel
    V = depth.shape[1]
    slow = torch.zeros(2, GRID.Z, GRID.Y, GRID.X, dtype=D)
    vs = GRID.voxel_size
    for z in range(GRID.Z):
        for y in range(GRID.Y):
            for x in range(GRID.X):
                centre = torch.tensor([GRID.xmin + (x + 0.5) * vs, GRID.ymin + (y + 0.5) * vs,
                                       GRID.zmin + (z + 0.5) * vs], dtype=D)
                values = []
                for v in range(V):
                    p = cam_T_ref[0, v, :3, :3] @ centre + cam_T_ref[0, v, :3, 3]
                    if p[2] <= 0:
                        continue
                    u_, v_ = float(3.0 * p[0] / p[2] + 2.5), float(3.0 * p[1] / p[2] + 2.0)
                    d = _slow_bilinear(depth[0, v], u_, v_, 0.05)
                    if d > 0 and d - float(p[2]) > -trunc:
                        values.append(min(1.0, max(-1.0, (d - float(p[2])) / trunc)))
                if values:
                    slow[0, z, y, x], slow[1, z, y, x] = sum(values) / len(values), 1.0
    torch.testing.assert_close(got[0], slow)
    assert 0 < float(slow[1].sum()) < slow[1].numel()


def test_a_wall_has_its_closed_form_tsdf_and_the_band_leaves_far_voxels_unknown():
    """A fronto-parallel wall at z = 3.3 seen from the ref origin: TSDF = (3.3 − z)/trunc near the wall (a plane
    is where bilinear depth is exact), and with a 1-voxel band the voxels 2+ voxels from it are unknown."""
    H, W = 40, 40
    pix = intrinsics(10.0, 10.0, (W - 1) / 2, (H - 1) / 2).to(D)[None]  # 1×1×4×4
    cam_T_ref = torch.eye(4, dtype=D)[None, None]
    depth = torch.full((1, 1, H, W), 3.3, dtype=D)
    trunc = 1.0
    got = projective_tsdf(depth, pix, cam_T_ref, GRID, truncation_m=trunc, band_voxels=1)
    z_centres = GRID.zmin + (torch.arange(GRID.Z, dtype=D) + 0.5) * GRID.voxel_size  # 0.25 … 3.75
    known = got[0, 1]  # Z×Y×X
    # The wall's points fill z-slice 6 (centre 3.25); the 1-voxel band is slices 5–7.
    for k, zc in enumerate(z_centres.tolist()):
        slab = known[k][:, 3:5]  # the columns about the optical axis: every ray there hits the wall
        if k in (5, 6, 7):
            assert bool((slab == 1).all()), (k, zc)
            torch.testing.assert_close(got[0, 0, k][:, 3:5], torch.full_like(slab, (3.3 - zc) / trunc))
        else:
            assert not bool(known[k].any()), (k, zc)
    band = surface_band(depth, pix, cam_T_ref, GRID, 1)
    assert bool(band[0, 5:8].all()) and not bool(band[0, :5].any())


@pytest.mark.parametrize("cell", [0.5, 0.25])
def test_cell_means_are_the_icp_baselines_downsampling(cell):
    """With cells aligned to the grid's corner at a multiple of the cell size, one point per occupied cube,
    the mean of its points — what core.baselines.icp.voxel_downsample gives — and nothing outside the grid."""
    depth, pix, cam_T_ref = _views()
    B, V, H, W = depth.shape
    xyz_cam, valid = depth_to_points(depth.reshape(V, H, W), pix.reshape(V, 4, 4))
    xyz = se3.apply(se3.invert(cam_T_ref.reshape(V, 4, 4)), xyz_cam).reshape(1, V * H * W, 3)
    valid = valid.reshape(1, V * H * W)
    points, points_valid = cell_mean_points(xyz, valid, GRID, cell)
    lo, hi = np.array(GRID.bounds_min), np.array(GRID.bounds_max)
    cloud = xyz[0][valid[0]].numpy()
    cloud = cloud[((cloud >= lo) & (cloud < hi)).all(1)]
    expected = voxel_downsample(cloud, cell)
    got = points[0][points_valid[0]].numpy()
    assert len(got) == len(expected) > 1
    np.testing.assert_allclose(got[np.lexsort(got.T)], expected[np.lexsort(expected.T)], atol=1e-9)


def test_cell_means_of_an_empty_cloud_are_one_invalid_row():
    points, points_valid = cell_mean_points(torch.zeros(2, 5, 3, dtype=D), torch.zeros(2, 5, dtype=torch.bool),
                                            GRID, 0.5)
    assert points.shape == (2, 1, 3) and not bool(points_valid.any())


def test_the_tsdf_is_the_same_under_bf16_autocast():
    depth, pix, cam_T_ref = (t.float() for t in _views())
    want = projective_tsdf(depth, pix, cam_T_ref, GRID, truncation_m=0.75, band_voxels=20)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = projective_tsdf(depth, pix, cam_T_ref, GRID, truncation_m=0.75, band_voxels=20)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, want)
