"""core.pipeline.flow_gate.gate_flow against a voxel-by-voxel reference."""

import itertools

import pytest
import torch

from core.errors import ShapeError
from core.pipeline.flow_gate import gate_flow


def _gate_loop(raw, occupancy, threshold, fill, moving):
    """Slow reference: a voxel keeps its flow when occupied, or when some occupied voxel within `fill`
    voxels per axis has flow longer than `moving`."""
    B, _, Z, Y, X = raw.shape
    out = torch.zeros_like(raw)
    occupied = occupancy[:, 0] >= threshold
    for b, z, y, x in itertools.product(range(B), range(Z), range(Y), range(X)):
        keep = bool(occupied[b, z, y, x])
        for dz, dy, dx in itertools.product(range(-fill, fill + 1), repeat=3):
            q = (z + dz, y + dy, x + dx)
            if fill and all(0 <= c < n for c, n in zip(q, (Z, Y, X))) and occupied[b][q] \
                    and float(raw[b, :, q[0], q[1], q[2]].norm()) > moving:
                keep = True
        if keep:
            out[b, :, z, y, x] = raw[b, :, z, y, x]
    return out


@pytest.mark.parametrize("fill", [0, 1, 2])
def test_gate_matches_the_voxel_loop(fill):
    torch.manual_seed(0)
    raw = torch.randn(2, 3, 5, 4, 6) * 0.6
    occupancy = torch.rand(2, 1, 5, 4, 6) ** 2
    torch.testing.assert_close(gate_flow(raw, occupancy, threshold=0.5, fill=fill, moving=0.5),
                               _gate_loop(raw, occupancy, 0.5, fill, 0.5))


def test_fill_opens_the_inside_of_a_moving_shell_only():
    """A moving object's observed shell opens its unobserved inside; free voxels beside a static surface
    stay closed."""
    raw = torch.zeros(1, 3, 7, 3, 12)
    occupancy = torch.zeros(1, 1, 7, 3, 12)
    raw[0, 0, 1:4, :, 1:4] = 2.0  # a moving object, x 1..3, z 1..3, moving +2 voxels along x
    occupancy[0, 0, 1, :, 1:4] = 1.0  # only its front face observed
    raw[0, 2, :, :, 8:11] = 0.2  # a static surface's neighbourhood with some small noise
    occupancy[0, 0, 3, :, 8:11] = 1.0
    paper = gate_flow(raw, occupancy, fill=0)
    filled = gate_flow(raw, occupancy, fill=1)
    assert paper[0, 0, 2].abs().sum() == 0 and (filled[0, 0, 2, :, 1:4] == 2.0).all()  # the inside, one voxel on
    assert filled[0, 0, 3].abs().sum() == 0  # two voxels behind the face: beyond fill=1
    assert torch.equal(filled[0, 2], paper[0, 2])  # the static surface: nothing more opens
    with pytest.raises(ShapeError, match="occupancy"):
        gate_flow(raw, occupancy[:, :, :4])
    with pytest.raises(ValueError, match="fill"):
        gate_flow(raw, occupancy, fill=-1)
