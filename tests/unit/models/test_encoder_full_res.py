"""The encoder's full-resolution branch: shapes, exact shift-equivariance of the branch, old configs.

Why the branch exists (core.models.encoder3d): three stride-2 stages make the paper's encoder equivariant
only to shifts by multiples of 8 voxels, so an object moved by 1-3 voxels gets different features.
"""

import pytest
import torch

from core.models.encoder3d import Encoder3D
from core.models.latent_map import Mapper
from core.models.registry import build_module
from core.presets import SMALL, TINY, Preset
from tests.unit.models.test_models import ODD_GRID


@pytest.mark.parametrize("zyx", [TINY.grid.shape_zyx, (7, 5, 9), (1, 3, 2)])
def test_full_res_encoder_keeps_grid_shape_unit_norm_and_trains_every_weight(zyx):
    enc = Encoder3D(in_channels=4, width=4, out_channels=6, full_res=3)
    feats = enc(torch.randn(2, 4, *zyx))
    assert feats.shape == (2, 6, *zyx)
    assert torch.allclose(feats.norm(dim=1), torch.ones(2, *zyx), atol=1e-4)
    feats.sum().backward()
    assert all(p.grad is not None for p in enc.parameters())


def _shift_x(vol: torch.Tensor, d: int) -> torch.Tensor:
    """Slow, obvious reference: content moves +d voxels along x, zeros come in."""
    out = torch.zeros_like(vol)
    for x in range(vol.shape[-1] - d):
        out[..., x + d] = vol[..., x]
    return out


def test_full_res_branch_follows_one_voxel_shifts_exactly():
    torch.manual_seed(0)
    enc = Encoder3D(in_channels=4, width=4, out_channels=6, full_res=5).eval()
    with torch.no_grad():  # silence the half-resolution path: what is left is the branch alone
        enc.fuse0.weight[:, :6] = 0.0
    vol = torch.zeros(1, 4, 8, 8, 16)
    vol[..., 3:6, 2:5, 4:9] = torch.randn(1, 4, 3, 3, 5)  # an "object" away from the borders
    with torch.no_grad():
        moved = enc(_shift_x(vol, 1))
        expected = _shift_x(enc(vol), 1)
    inner = (..., slice(None), slice(None), slice(2, 14))  # away from the x border the zero fill touches
    assert torch.allclose(moved[inner], expected[inner], atol=1e-5)


def test_paper_layers_alone_do_not_follow_one_voxel_shifts():
    """The measurement that motivated the branch, as a check that it stays true of the paper's layers."""
    torch.manual_seed(0)
    enc = Encoder3D(in_channels=4, width=4, out_channels=6).eval()
    vol = torch.randn(1, 4, 16, 16, 32)
    with torch.no_grad():
        moved, expected = enc(_shift_x(vol, 1)), _shift_x(enc(vol), 1)
    cos = (moved * expected).sum(1)[..., 4:-4]  # unit features
    assert cos.mean() < 0.95


def test_mapper_configs_without_full_res_still_build_and_presets_still_read():
    old = Mapper(grid=ODD_GRID, width=4, feature_dim=6).config()
    old.pop("full_res")  # a bundle written before the branch existed
    rebuilt = build_module("mapper", old)
    assert rebuilt.full_res == 0 and not hasattr(rebuilt.encoder, "skip0")
    d = SMALL.to_dict()
    d.pop("encoder_full_res")
    assert Preset.from_dict(d).encoder_full_res == 0
    assert Preset.from_dict(SMALL.to_dict()) == SMALL
