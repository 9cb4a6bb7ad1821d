"""shift_voxels against a per-voxel loop; a shift and its inverse give back what stayed inside."""

import itertools

import pytest
import torch

from core.errors import ShapeError
from core.geometry.shift import shift_voxels


def _shift_loop(volume: torch.Tensor, offset_xyz: tuple[int, int, int]) -> torch.Tensor:
    dx, dy, dz = offset_xyz
    out = torch.zeros_like(volume)
    Z, Y, X = volume.shape[2:]
    for z, y, x in itertools.product(range(Z), range(Y), range(X)):
        if 0 <= z + dz < Z and 0 <= y + dy < Y and 0 <= x + dx < X:
            out[..., z + dz, y + dy, x + dx] = volume[..., z, y, x]
    return out


@pytest.mark.parametrize("offset", [(0, 0, 0), (1, 0, 0), (0, -2, 0), (0, 0, 3), (2, -1, -3), (-4, 3, 1), (5, 0, 0)])
def test_shift_voxels_matches_the_loop(offset):
    volume = torch.randn(2, 3, 4, 5, 5)
    assert torch.equal(shift_voxels(volume, offset), _shift_loop(volume, offset))


def test_shift_and_back_keeps_what_stayed_inside():
    volume = torch.randn(1, 2, 6, 4, 7)
    offset = (2, -1, 3)
    back = shift_voxels(shift_voxels(volume, offset), tuple(-o for o in offset))
    inside = shift_voxels(shift_voxels(torch.ones_like(volume), offset), tuple(-o for o in offset))
    assert torch.equal(back, volume * inside)
    assert 0 < int(inside[0, 0].sum()) < volume[0, 0].numel()


def test_shift_voxels_rejects_a_non_volume():
    with pytest.raises(ShapeError, match="volume"):
        shift_voxels(torch.zeros(2, 3, 4), (1, 0, 0))
