"""Shapes of every model at the tiny preset (odd sizes included), rebuild from config, map fusion."""

import pytest
import torch

from core.geometry import se3
from core.geometry.camera import intrinsics_from_fov
from core.geometry.grid import GridConfig
from core.geometry.voxelize import voxelize
from core.models.encoder3d import Encoder3D
from core.models.input_volume import input_volume
from core.models.latent_map import Mapper, RunningMap, masked_average
from core.models.net2d import Net2D
from core.models.occupancy_head import OccupancyHead
from core.models.projector import Projector
from core.models.registry import MODULE_KINDS, build_module, kind_of
from core.presets import TINY

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]
ODD_GRID = GridConfig(xmin=-4.5, xmax=4.5, ymin=-2.5, ymax=2.5, zmin=-3.5, zmax=3.5, Z=7, Y=5, X=9)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("zyx", [TINY.grid.shape_zyx, (7, 5, 9), (1, 3, 2)])
def test_encoder_keeps_grid_resolution_and_unit_norm(device, zyx):
    enc = Encoder3D(in_channels=4, width=4, out_channels=6).to(device)
    feats = enc(torch.randn(2, 4, *zyx, device=device))
    assert feats.shape == (2, 6, *zyx)
    assert torch.allclose(feats.norm(dim=1), torch.ones(2, *zyx, device=device), atol=1e-4)
    feats.sum().backward()
    assert all(p.grad is not None for p in enc.parameters())


@pytest.mark.parametrize("stride,H,W", [(1, 64, 192), (2, 64, 192), (2, 33, 47)])
def test_net2d_shapes(stride, H, W):
    net = Net2D(widths=(4, 8), out_channels=5, stride=stride)
    out = net(torch.rand(2, 3, H, W))
    assert out.shape == (2, 5, -(-H // stride), -(-W // stride))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("grid,H,W", [(TINY.grid, 32, 96), (ODD_GRID, 9, 13)])
def test_projector_shapes(device, grid, H, W):
    proj = Projector(grid=grid, in_channels=4, out_channels=3, depth_planes=16, normalize=False).to(device)
    pix_T_cam = intrinsics_from_fov(H, W, 90.0).expand(2, 4, 4).to(device)
    out = proj(torch.randn(2, 4, *grid.shape_zyx, device=device), pix_T_cam,
               torch.eye(4, device=device).expand(2, 4, 4), H, W)
    assert out.shape == (2, 3, H, W)


def test_occupancy_head_shapes_and_range():
    head = OccupancyHead(in_channels=4)
    p = head.probabilities(torch.randn(2, 4, 7, 5, 9))
    assert p.shape == (2, 1, 7, 5, 9) and p.min() >= 0 and p.max() <= 1


def test_input_volume_channels(make_views):
    grid = TINY.grid
    rgb, depth, K, cam_T_ref = make_views(1, 1, 16, 48, grid)
    vol, in_view = input_volume(rgb[:, 0], depth[:, 0], K[:, 0], cam_T_ref[:, 0], grid)
    assert vol.shape == (1, 4, *grid.shape_zyx) and in_view.shape == (1, 1, *grid.shape_zyx)
    from core.geometry.camera import depth_to_points
    xyz, valid = depth_to_points(depth[:, 0], K[:, 0])
    assert torch.equal(vol[:, :1], voxelize(se3.apply(se3.invert(cam_T_ref[:, 0]), xyz), grid, valid))
    assert (vol[:, 1:] * (1 - in_view)).abs().max() == 0  # colour only where the view sees the voxel
    assert in_view.sum() > 0 and (1 - in_view).sum() > 0


def test_input_volume_splat_occupancy(make_views):
    grid = TINY.grid
    rgb, depth, K, cam_T_ref = make_views(1, 2, 16, 48, grid)
    binary, _ = input_volume(rgb[:, 0], depth[:, 0], K[:, 0], cam_T_ref[:, 0], grid)
    vol, _ = input_volume(rgb[:, 0], depth[:, 0], K[:, 0], cam_T_ref[:, 0], grid, occupancy="splat")
    from core.geometry.camera import depth_to_points
    from core.geometry.splat import surface_splat
    xyz, valid = depth_to_points(depth[:, 0], K[:, 0])
    expected = surface_splat(xyz, valid, K[:, 0], cam_T_ref[:, 0], grid).clamp(max=1.0)
    torch.testing.assert_close(vol[:, :1], expected)  # the clamped surface splat
    torch.testing.assert_close(vol[:, 1:], binary[:, 1:])  # colour unchanged
    assert float(vol[:, :1].min()) >= 0 and float(vol[:, :1].max()) <= 1
    assert float(vol[:, :1][binary[:, :1] > 0].sum()) > 0
    # fused over views by max: a view fused with itself is that view
    from core.models.egomotion_inputs import fused_input_volume
    twice = fused_input_volume(rgb[:, :1].repeat(1, 2, 1, 1, 1), depth[:, :1].repeat(1, 2, 1, 1),
                               K[:, :1].repeat(1, 2, 1, 1), cam_T_ref[:, :1].repeat(1, 2, 1, 1), grid,
                               occupancy="splat")
    torch.testing.assert_close(twice[:, :1], vol[:, :1])
    with pytest.raises(ValueError):
        input_volume(rgb[:, 0], depth[:, 0], K[:, 0], cam_T_ref[:, 0], grid, occupancy="dense")


def test_masked_average_matches_loop_and_running_map():
    feats = torch.randn(1, 3, 2, 2, 2, 3)
    masks = (torch.rand(1, 3, 1, 2, 2, 3) > 0.5).float()
    masks[..., 0, 0, 0] = 0  # one voxel no view sees: plain mean
    fused = masked_average(feats, masks)
    for z in range(2):
        for y in range(2):
            for x in range(3):
                m = masks[0, :, 0, z, y, x]
                w = m if m.sum() > 0 else torch.ones(3)
                ref = (feats[0, :, :, z, y, x] * w[:, None]).sum(0) / w.sum()
                assert torch.allclose(fused[0, :, z, y, x], ref / ref.norm(), atol=1e-5)
    state = RunningMap.empty(1, 2, GridConfig(xmin=0, xmax=3, ymin=0, ymax=2, zmin=0, zmax=2, Z=2, Y=2, X=3))
    for v in range(3):
        state = state.update(feats[:, v], masks[:, v])
    seen = masks.sum(dim=1)[:, 0] > 0  # B×Z×Y×X
    assert torch.allclose(state.features().permute(0, 2, 3, 4, 1)[seen], fused.permute(0, 2, 3, 4, 1)[seen], atol=1e-5)


def test_mapper_shapes(make_views):
    mapper = Mapper(grid=TINY.grid, width=4, feature_dim=6)
    rgb, depth, K, cam_T_ref = make_views(2, 3, 16, 48, TINY.grid)
    feats, in_view, occ = mapper.encode_views(rgb, depth, K, cam_T_ref)
    assert feats.shape == (2, 3, 6, *TINY.grid.shape_zyx)
    assert in_view.shape == occ.shape == (2, 3, 1, *TINY.grid.shape_zyx)
    assert mapper(rgb, depth, K, cam_T_ref).shape == (2, 6, *TINY.grid.shape_zyx)


@pytest.mark.parametrize("module", [
    Encoder3D(in_channels=4, width=4, out_channels=6), Mapper(grid=ODD_GRID, width=4, feature_dim=6),
    Projector(grid=ODD_GRID, in_channels=6, out_channels=3, depth_planes=16), Net2D(widths=(4, 8), out_channels=5),
    OccupancyHead(in_channels=6)], ids=lambda m: type(m).__name__)
def test_registry_rebuilds_every_kind_from_config(module):
    kind = kind_of(module)
    assert kind in MODULE_KINDS
    rebuilt = build_module(kind, module.config())
    assert type(rebuilt) is type(module) and rebuilt.config() == module.config()
    assert {k: v.shape for k, v in rebuilt.state_dict().items()} == {k: v.shape for k, v in module.state_dict().items()}
