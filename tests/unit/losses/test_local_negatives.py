"""Local negatives of the 3D contrastive loss against a voxel-by-voxel reference."""

import pytest
import torch

from core.losses.local_negatives import local_negative_loss, neighbour_offsets


def test_offsets_cover_the_window_but_never_the_centre():
    g = torch.Generator().manual_seed(0)
    d = neighbour_offsets(20000, 1, g)
    assert d.abs().max() == 1 and not (d == 0).all(dim=1).any()
    assert len({tuple(r) for r in d.tolist()}) == 26


def _slow(top, bottom, valid, radius, samples, seed, beta=1.2, margin=0.2):
    """Replays the sampler with the same generator, then scores each kept pair in a Python loop."""
    from core.losses.contrastive import sample_positions

    g = torch.Generator().manual_seed(seed)
    B, C, Z, Y, X = top.shape
    rows, cols = sample_positions(valid.reshape(B, -1) > 0.5, samples, g)
    offsets = neighbour_offsets(rows.numel(), radius, g)
    hinges = []
    for b, c, (dz, dy, dx) in zip(rows.tolist(), cols.tolist(), offsets.tolist()):
        z, y, x = c // (Y * X), (c // X) % Y, c % X
        qz, qy, qx = z + dz, y + dy, x + dx
        if not (0 <= qz < Z and 0 <= qy < Y and 0 <= qx < X) or valid[b, 0, qz, qy, qx] < 0.5:
            continue
        d = torch.sqrt(((top[b, :, z, y, x] - bottom[b, :, qz, qy, qx]) ** 2).sum() + 1e-8)
        hinges.append(torch.relu(beta - d + margin))
    assert len(hinges) >= 5  # the case exercises the loss
    h = torch.stack(hinges)
    return h.sum() / (h > 0).sum().clamp(min=1)


@pytest.mark.parametrize("radius", [1, 2])
def test_loss_matches_the_loop_and_pushes_neighbours_apart(radius):
    g = torch.Generator().manual_seed(3)
    top = torch.nn.functional.normalize(torch.randn(2, 4, 4, 3, 6, generator=g), dim=1).requires_grad_(True)
    bottom = torch.nn.functional.normalize(torch.randn(2, 4, 4, 3, 6, generator=g), dim=1)
    valid = (torch.rand(2, 1, 4, 3, 6, generator=g) > 0.3).float()
    fast = local_negative_loss(top, bottom, valid, radius=radius, samples=24, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(fast, _slow(top, bottom, valid, radius, 24, 7))
    fast.backward()
    assert top.grad.abs().sum() > 0
    # features identical everywhere: every neighbour is at distance 0, each hinge is β + α
    same = torch.ones(1, 2, 3, 3, 3) / 2 ** 0.5
    loss = local_negative_loss(same, same, torch.ones(1, 1, 3, 3, 3), radius=1, samples=8,
                               generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(loss, torch.tensor(1.4), atol=1e-3, rtol=0)


def test_no_observed_neighbour_gives_zero_with_a_gradient_path():
    top = torch.randn(1, 2, 3, 3, 3, requires_grad=True)
    valid = torch.zeros(1, 1, 3, 3, 3)
    valid[0, 0, 1, 1, 1] = 1.0  # one observed voxel: none of its neighbours is
    loss = local_negative_loss(top, top.detach(), valid, radius=1, samples=4)
    assert loss.item() == 0.0
    loss.backward()
    assert top.grad is not None


def test_pretrain_refuses_local_negatives_for_regression():
    from core.tasks.pretrain import PretrainConfig
    from core.geometry.grid import GridConfig

    grid = GridConfig(xmin=-1, xmax=1, ymin=-1, ymax=1, zmin=-1, zmax=1, Z=2, Y=2, X=2)
    with pytest.raises(ValueError, match="contrastive"):
        PretrainConfig(grid=grid, objective="regression", coeff_local_negatives=1.0)
