"""core.losses.local_matching against a loop over the window written out, and its behaviour at the edges."""

import math

import pytest
import torch
import torch.nn.functional as F

from core.errors import ShapeError
from core.losses.local_matching import local_matching_loss


def _one_voxel(shape, zyx):
    valid = torch.zeros(shape)
    valid[(0, 0, *zyx)] = 1.0
    return valid


def _reference(f0, f1, p_xyz, flow_xyz, radius, temperature):
    """Cross-entropy for one voxel, integer flow: cosines by direct indexing, softmax by hand."""
    x, y, z = p_xyz
    a = f0[0, :, z, y, x]
    logits, centre = [], None
    for dz in range(-radius[2], radius[2] + 1):
        for dy in range(-radius[1], radius[1] + 1):
            for dx in range(-radius[0], radius[0] + 1):
                qx, qy, qz = x + flow_xyz[0] + dx, y + flow_xyz[1] + dy, z + flow_xyz[2] + dz
                inside = 0 <= qx < f1.shape[-1] and 0 <= qy < f1.shape[-2] and 0 <= qz < f1.shape[-3]
                if not inside:  # no candidate there
                    continue
                b = f1[0, :, qz, qy, qx]
                cos = float(a @ b) / (float(a.norm()) * float(b.norm()))
                if (dx, dy, dz) == (0, 0, 0):
                    centre = len(logits)
                logits.append(cos / temperature)
    m = max(logits)
    log_z = m + math.log(sum(math.exp(v - m) for v in logits))
    return log_z - logits[centre], int(max(range(len(logits)), key=logits.__getitem__) == centre)


@pytest.mark.parametrize("radius", [(1, 1, 1), (2, 1, 2)])
def test_one_voxel_matches_the_window_written_out(radius):
    g = torch.Generator().manual_seed(0)
    f0 = torch.randn(1, 5, 6, 4, 7, generator=g)
    f1 = torch.randn(1, 5, 6, 4, 7, generator=g)
    flow = torch.zeros(1, 3, 6, 4, 7)
    flow[0, :, 2, 1, 3] = torch.tensor([2.0, 1.0, -1.0])  # (x, y, z) of voxel z=2, y=1, x=3
    loss, hit = local_matching_loss(f0, f1, flow, _one_voxel((1, 1, 6, 4, 7), (2, 1, 3)), radius=radius,
                                    temperature=0.2, samples=3)
    ref_loss, ref_hit = _reference(f0, f1, (3, 1, 2), (2, 1, -1), radius, 0.2)
    assert abs(float(loss) - ref_loss) < 1e-4
    assert float(hit) == ref_hit


def test_features_that_move_with_their_content_are_found_and_static_ones_are_not():
    g = torch.Generator().manual_seed(1)
    f0 = F.normalize(torch.randn(2, 8, 6, 5, 9, generator=g), dim=1)
    shift = 2
    f1 = torch.roll(f0, shifts=shift, dims=-1)  # content moved +2 voxels along x
    flow = torch.zeros(2, 3, 6, 5, 9)
    flow[:, 0] = shift
    valid = torch.zeros(2, 1, 6, 5, 9)
    valid[..., : 9 - shift] = 1.0  # where p + flow stays inside the grid
    moving_loss, moving_hit = local_matching_loss(f0, f1, flow, valid, samples=64,
                                                  generator=torch.Generator().manual_seed(0))
    static_loss, static_hit = local_matching_loss(f0, f0.clone(), flow, valid, samples=64,
                                                  generator=torch.Generator().manual_seed(0))
    assert float(moving_hit) == 1.0 and float(static_hit) < 0.2
    assert float(moving_loss) < float(static_loss) - 1.0


def test_matches_outside_the_grid_are_dropped_and_an_empty_selection_gives_zero_with_a_gradient():
    f0 = torch.randn(1, 4, 3, 3, 3, requires_grad=True)
    f1 = torch.randn(1, 4, 3, 3, 3)
    flow = torch.full((1, 3, 3, 3, 3), 5.0)  # every match leaves the grid
    loss, hit = local_matching_loss(f0, f1, flow, torch.ones(1, 1, 3, 3, 3), samples=4)
    assert float(loss) == 0.0 and float(hit) == 0.0
    loss.backward()
    assert f0.grad is not None and float(f0.grad.abs().sum()) == 0.0


def test_gradients_reach_both_volumes():
    g = torch.Generator().manual_seed(2)
    f0 = torch.randn(1, 4, 5, 3, 5, generator=g, requires_grad=True)
    f1 = torch.randn(1, 4, 5, 3, 5, generator=g, requires_grad=True)
    loss, _ = local_matching_loss(f0, f1, torch.zeros(1, 3, 5, 3, 5), torch.ones(1, 1, 5, 3, 5), samples=8,
                                  generator=torch.Generator().manual_seed(0))
    loss.backward()
    assert float(f0.grad.abs().sum()) > 0 and float(f1.grad.abs().sum()) > 0


def test_bad_shapes_and_temperature_are_named():
    f = torch.zeros(1, 2, 3, 3, 3)
    with pytest.raises(ShapeError, match="flow"):
        local_matching_loss(f, f, torch.zeros(1, 2, 3, 3, 3), torch.ones(1, 1, 3, 3, 3))
    with pytest.raises(ShapeError, match="temperature"):
        local_matching_loss(f, f, torch.zeros(1, 3, 3, 3, 3), torch.ones(1, 1, 3, 3, 3), temperature=0.0)
