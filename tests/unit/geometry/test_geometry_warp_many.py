"""core.geometry.warp_many against PyTorch's 3D trilinear sampler (the slow, obvious reference): values at
points inside, on the fading border and far outside; gradients w.r.t. the volume and the points; and the
rigid warp of one volume under R motions against `warp_rigid` of each."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_rigid
from core.geometry.warp_many import sample_via_slices, warp_rigid_many


def reference_samples(vol: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    """vol 1×C×Z×Y×X, xyz R×P×3 mem -> R×C×P through F.grid_sample's 3D path, one point set at a time."""
    Z, Y, X = vol.shape[-3:]
    size = torch.tensor([X, Y, Z], dtype=xyz.dtype)
    out = [F.grid_sample(vol, (2 * pts / (size - 1) - 1).reshape(1, 1, 1, -1, 3), align_corners=True).reshape(vol.shape[1], -1)
           for pts in xyz]
    return torch.stack(out)  # R×C×P


def test_samples_equal_the_3d_sampler_inside_on_the_border_and_outside():
    g = torch.Generator().manual_seed(0)
    vol = torch.randn(1, 3, 5, 4, 6, generator=g, dtype=torch.float64)
    Z, Y, X = 5, 4, 6
    inside = torch.rand(2, 50, 3, generator=g, dtype=torch.float64) * torch.tensor([X - 1, Y - 1, Z - 1])
    border = torch.tensor([[-0.5, 1, 1], [X - 0.5, 1, 1], [2, -0.7, 1], [2, Y - 0.2, 1], [2, 1, -0.3], [2, 1, Z - 0.6],
                           [-1.0, -1.0, -1.0], [X, Y, Z]], dtype=torch.float64)
    far = torch.tensor([[-7, 1, 1], [2, -9, 1], [2, 1, -4], [20, 1, 1], [2, 11, 1], [2, 1, 30], [2, 7.5, 2.5],
                        [3, 2, 9.9]], dtype=torch.float64)
    points = torch.cat([inside, torch.stack([border, far])], dim=1)  # 2×58×3
    fast = sample_via_slices(vol, points)
    assert fast.shape == (2, 3, 58)
    torch.testing.assert_close(fast, reference_samples(vol, points), rtol=1e-9, atol=1e-9)
    assert (fast[1, :, 50 + 8:] == 0).all()  # more than a voxel outside: zero


def test_a_thin_volume_works_and_a_one_voxel_x_is_refused():
    g = torch.Generator().manual_seed(1)
    thin = torch.randn(1, 2, 3, 1, 4, generator=g, dtype=torch.float64)  # Y = 1
    points = torch.rand(1, 30, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 2.0, 4.0]) - 0.5
    # reference for a size-1 axis: resample.sample_volume_at pads it (align_corners would map all y onto it)
    from core.geometry.resample import sample_volume
    torch.testing.assert_close(sample_via_slices(thin, points), sample_volume(thin, points), rtol=1e-9, atol=1e-9)
    with pytest.raises(ShapeError, match="X must be at least 2"):
        sample_via_slices(torch.zeros(1, 1, 2, 2, 1), points)
    with pytest.raises(ShapeError, match="1×C×Z×Y×X"):
        sample_via_slices(torch.zeros(2, 1, 2, 2, 2), points)


def test_gradients_equal_the_3d_sampler():
    g = torch.Generator().manual_seed(2)
    vol = torch.randn(1, 2, 4, 3, 5, generator=g, dtype=torch.float64, requires_grad=True)
    points = (torch.rand(3, 20, 3, generator=g, dtype=torch.float64) * torch.tensor([5.0, 4.0, 5.0]) - 0.5)
    points = (points + 0.013).requires_grad_(True)  # off the integer lattice, where the gradient is defined
    weights = torch.randn(3, 2, 20, generator=g, dtype=torch.float64)
    (sample_via_slices(vol, points) * weights).sum().backward()
    fast = (vol.grad.clone(), points.grad.clone())
    vol.grad, points.grad = None, None
    (reference_samples(vol, points) * weights).sum().backward()
    torch.testing.assert_close(fast[0], vol.grad)
    torch.testing.assert_close(fast[1], points.grad)


def test_rigid_warp_of_one_volume_under_many_motions_equals_warp_rigid():
    grid = GridConfig(xmin=-8.0, xmax=8.0, ymin=-2.0, ymax=2.0, zmin=-8.0, zmax=8.0, Z=16, Y=4, X=16)
    g = torch.Generator().manual_seed(3)
    vol = torch.randn(1, 4, 16, 4, 16, generator=g)
    angles = torch.randn(5, 3, generator=g) * 0.05
    b_T_a = se3.from_rt(se3.euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2]), torch.randn(5, 3, generator=g))
    fast = warp_rigid_many(vol, b_T_a, grid)
    assert fast.shape == (5, 4, 16, 4, 16)
    # float32: the 2D sampler normalises a (Z+2)(Y+2)-row coordinate, so agreement is to ~1e-5 here
    torch.testing.assert_close(fast, warp_rigid(vol.expand(5, -1, -1, -1, -1), b_T_a, grid), rtol=0, atol=5e-5)
