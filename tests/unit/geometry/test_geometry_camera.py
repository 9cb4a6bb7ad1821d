"""camera: intrinsics conventions, project∘unproject, depth <-> points against a slow loop."""

import math

import torch

from core.geometry import camera

D = torch.float64


def test_intrinsics_layout_and_fov():
    K = camera.intrinsics(torch.tensor([100.0, 50.0], dtype=D), 90.0, 31.5, 20.0)
    assert K.shape == (2, 4, 4) and K.dtype == D
    assert K[1, 0, 0] == 50.0 and K[1, 1, 1] == 90.0 and K[0, 0, 2] == 31.5 and K[0, 1, 2] == 20.0
    assert K[0, 2, 2] == 1.0 and K[0, 3, 3] == 1.0
    Kf = camera.intrinsics_from_fov(48, 64, 90.0, dtype=D)
    # 90° hfov: the image edge u = -0.5 is at x/z = -1
    assert torch.allclose(Kf[0, 0, 0], torch.tensor(32.0, dtype=D))
    assert Kf[0, 0, 2] == 31.5 and Kf[0, 1, 2] == 23.5
    uv, _ = camera.project(Kf, torch.tensor([[[-1.0, 0.0, 1.0]]], dtype=D))
    assert torch.allclose(uv[0, 0, 0], torch.tensor(-0.5, dtype=D))


def test_scale_intrinsics_keeps_pixel_edges():
    K = camera.intrinsics_from_fov(48, 64, 70.0, dtype=D)
    K2 = camera.scale_intrinsics(K, 0.5, 0.25)
    xyz = torch.tensor([[[0.3, -0.2, 2.0], [-1.0, 0.7, 3.0]]], dtype=D)
    uv, _ = camera.project(K, xyz)
    uv2, _ = camera.project(K2, xyz)
    s = torch.tensor([0.5, 0.25], dtype=D)
    assert torch.allclose(uv2, s * (uv + 0.5) - 0.5, atol=1e-12)
    # the half-size camera still sees the same field of view: centre at (W'-1)/2
    assert K2[0, 0, 2] == 15.5 and K2[0, 1, 2] == 5.5


def test_project_unproject_round_trip():
    g = torch.Generator().manual_seed(0)
    K = camera.intrinsics(torch.tensor([120.0, 80.0], dtype=D), torch.tensor([110.0, 85.0], dtype=D), 30.0, 20.0)
    xyz = torch.randn(2, 50, 3, generator=g, dtype=D)
    xyz[..., 2] = xyz[..., 2].abs() + 0.5
    uv, z = camera.project(K, xyz)
    assert torch.allclose(camera.unproject(K, uv, z), xyz, atol=1e-12)


def test_depth_to_points_matches_slow_loop_and_round_trips():
    g = torch.Generator().manual_seed(1)
    B, H, W = 2, 5, 7
    K = camera.intrinsics(torch.tensor([6.0, 5.0], dtype=D), torch.tensor([6.5, 4.0], dtype=D), 3.2, 1.9)
    depth = torch.rand(B, H, W, generator=g, dtype=D) * 4 + 1
    depth[0, 1, 2] = 0.0
    depth[1, 4, 6] = float("nan")
    xyz, valid = camera.depth_to_points(depth, K)
    for b in range(B):
        fx, fy, cx, cy = K[b, 0, 0], K[b, 1, 1], K[b, 0, 2], K[b, 1, 2]
        for v in range(H):
            for u in range(W):
                d = depth[b, v, u]
                ok = bool(torch.isfinite(d) and d > 0)
                assert bool(valid[b, v * W + u]) == ok
                if ok:
                    expected = torch.stack([(u - cx) * d / fx, (v - cy) * d / fy, d])
                    assert torch.allclose(xyz[b, v * W + u], expected, atol=1e-12)
    back = camera.points_to_depth(xyz, K, H, W, valid)
    clean = torch.nan_to_num(depth, nan=0.0)
    assert torch.allclose(back, clean, atol=1e-12)


def test_points_to_depth_keeps_nearest_and_drops_outside():
    K = camera.intrinsics(10.0, 10.0, 2.0, 2.0, dtype=D)
    pts = torch.tensor([[[0.0, 0.0, 5.0], [0.0, 0.0, 3.0], [0.0, 0.0, -1.0], [10.0, 0.0, 1.0]]], dtype=D)
    depth = camera.points_to_depth(pts, K, 5, 5)
    assert depth[0, 2, 2] == 3.0
    assert (depth > 0).sum() == 1
