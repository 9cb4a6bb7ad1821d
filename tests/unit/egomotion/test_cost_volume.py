"""Cost volume vs a slow per-voxel reference; candidate rotation set."""

import pytest
import torch

from core.models import cost_volume
from core.models.cost_volume import cross_correlation_3d, displacements, mean_correlation_3d
from core.models.egomotion_rotations import candidate_rotations
from core.geometry import se3


def _slow_cost(f0, f1, radius):
    B, C, Z, Y, X = f0.shape
    d = displacements(radius).long()
    out = torch.zeros(B, len(d), Z, Y, X, dtype=f0.dtype)
    for i, (dx, dy, dz) in enumerate(d.tolist()):
        for z in range(Z):
            for y in range(Y):
                for x in range(X):
                    zz, yy, xx = z + dz, y + dy, x + dx
                    if 0 <= zz < Z and 0 <= yy < Y and 0 <= xx < X:
                        out[:, i, z, y, x] = (f0[:, :, z, y, x] * f1[:, :, zz, yy, xx]).sum(1)
    return out


def test_cost_volume_matches_slow_reference():
    g = torch.Generator().manual_seed(0)
    f0 = torch.randn(2, 3, 3, 2, 4, generator=g)
    f1 = torch.randn(2, 3, 3, 2, 4, generator=g)
    r = (1, 1, 2)
    fast = cross_correlation_3d(f0, f1, r)
    assert fast.shape == (2, 3 * 3 * 5, 3, 2, 4)
    torch.testing.assert_close(fast, _slow_cost(f0, f1, r), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(cross_correlation_3d(f0, f1, r, normalize=True), fast / 3)


def test_cost_volume_gradients_match_autograd_through_the_slow_reference():
    """The hand-written backward (one buffer per direction) against autograd through the per-voxel loop,
    for f0 and f1 together and each alone (the other frozen)."""
    g = torch.Generator().manual_seed(1)
    r = (2, 0, 1)
    base0 = torch.randn(2, 3, 3, 2, 4, generator=g, dtype=torch.float64)
    base1 = torch.randn(2, 3, 3, 2, 4, generator=g, dtype=torch.float64)
    weights = torch.randn(2, 5 * 1 * 3, 3, 2, 4, generator=g, dtype=torch.float64)
    for grad0, grad1 in ((True, True), (True, False), (False, True)):
        f0 = base0.clone().requires_grad_(grad0)
        f1 = base1.clone().requires_grad_(grad1)
        inputs = [t for t in (f0, f1) if t.requires_grad]
        fast = torch.autograd.grad((cross_correlation_3d(f0, f1, r) * weights).sum(), inputs)
        slow = torch.autograd.grad((_slow_cost(f0, f1, r) * weights).sum(), inputs)
        for a, b in zip(fast, slow):
            torch.testing.assert_close(a, b)


@pytest.mark.parametrize("tile_slices", [1, 2, 3])
def test_z_tiled_loops_equal_the_slow_reference_and_the_whole_volume_bit_for_bit(monkeypatch, tile_slices):
    """On CPU the displacement loops run over z-slabs (`_z_tile`); slabs of 1-3 slices of a 5-slice volume
    (a last slab shorter than the others, a z-radius wider than a slab) give the slow loop's costs and
    gradients, and the same bits as one slab of the whole volume (each element sums its displacements in
    the same order)."""
    g = torch.Generator().manual_seed(2)
    r = (1, 1, 2)
    base0 = torch.randn(2, 3, 5, 2, 4, generator=g, dtype=torch.float64)
    base1 = torch.randn(2, 3, 5, 2, 4, generator=g, dtype=torch.float64)
    weights = torch.randn(2, 3 * 3 * 5, 5, 2, 4, generator=g, dtype=torch.float64)

    def run():
        f0, f1 = base0.clone().requires_grad_(True), base1.clone().requires_grad_(True)
        cost = cross_correlation_3d(f0, f1, r)
        return (cost.detach(), *torch.autograd.grad((cost * weights).sum(), (f0, f1)))

    whole = run()
    slab_bytes = 2 * 3 * 2 * 4 * base0.element_size()  # one z-slice of the B×C×z×Y×X operand
    monkeypatch.setattr(cost_volume, "_TILE_BYTES", tile_slices * slab_bytes)
    assert cost_volume._z_tile(base0) == tile_slices
    tiled = run()
    for a, b in zip(tiled, whole):
        assert torch.equal(a, b)
    f0, f1 = base0.clone().requires_grad_(True), base1.clone().requires_grad_(True)
    slow = _slow_cost(f0, f1, r)
    torch.testing.assert_close(tiled[0], slow.detach())
    for a, b in zip(tiled[1:], torch.autograd.grad((slow * weights).sum(), (f0, f1))):
        torch.testing.assert_close(a, b)


def test_mean_correlation_matches_the_slow_cost_averaged_over_space():
    g = torch.Generator().manual_seed(2)
    ref = torch.randn(2, 3, 3, 2, 4, generator=g, dtype=torch.float64)
    queries = torch.randn(2, 5, 3, 3, 2, 4, generator=g, dtype=torch.float64)
    r = (1, 1, 2)
    fast = mean_correlation_3d(ref, queries, r)  # 2×5×45
    assert fast.shape == (2, 5, 45)
    for b in range(2):
        for i in range(5):
            slow = _slow_cost(ref[b:b + 1].float(), queries[b:b + 1, i].float(), r).mean((2, 3, 4))[0]  # D
            torch.testing.assert_close(fast[b, i].float(), slow, rtol=1e-5, atol=1e-5)


def test_mean_correlation_gradients_match_the_loop():
    g = torch.Generator().manual_seed(3)
    ref = torch.randn(1, 2, 3, 2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    queries = torch.randn(1, 3, 2, 3, 2, 3, generator=g, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(1, 3, 27, generator=g, dtype=torch.float64)
    (mean_correlation_3d(ref, queries, (1, 1, 1)) * weights).sum().backward()
    fast = (ref.grad.clone(), queries.grad.clone())
    ref.grad, queries.grad = None, None
    loop = torch.stack([cross_correlation_3d(ref, queries[:, i], (1, 1, 1)).mean((2, 3, 4)) for i in range(3)], 1)
    (loop * weights).sum().backward()
    torch.testing.assert_close(fast[0], ref.grad)
    torch.testing.assert_close(fast[1], queries.grad)


def test_cost_volume_peaks_at_true_shift():
    g = torch.Generator().manual_seed(1)
    f0 = torch.nn.functional.normalize(torch.randn(1, 8, 6, 6, 6, generator=g), dim=1)
    f1 = torch.roll(f0, shifts=(1, -1), dims=(4, 2))  # f1(p + (1, 0, -1)) = f0(p): dx=+1, dz=-1
    cost = cross_correlation_3d(f0, f1, (1, 1, 1))[..., 1:-1, 1:-1, 1:-1].mean((2, 3, 4))  # 1×27
    d = displacements((1, 1, 1))
    assert d[cost.argmax()].tolist() == [1.0, 0.0, -1.0]


def test_candidate_rotations():
    R = candidate_rotations((2.0, 4.0, 2.0))
    assert R.shape == (27, 4, 4)
    torch.testing.assert_close(R[13], torch.eye(4))
    assert bool(se3.is_rigid(R).all())
    # product order (rx, ry, rz), rz fastest: (0, +1, 0) offsets sit at 1·9 + 2·3 + 1 = 16 -> yaw +4°
    torch.testing.assert_close(R[16, :3, :3], se3.yaw_to_matrix(torch.deg2rad(torch.tensor(4.0))))
    corner = se3.euler_to_matrix(*torch.deg2rad(torch.tensor([2.0, 4.0, 2.0])))
    torch.testing.assert_close(R[26, :3, :3], corner)
