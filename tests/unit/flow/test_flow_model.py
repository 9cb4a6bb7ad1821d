"""3D flow module pieces: synthetic rigid flow direction, flow resampling, module shapes and init."""

import math

import pytest
import torch

from core.geometry import se3
from core.geometry.grid import GridConfig, voxel_centers_mem
from core.geometry.resample import warp_flow, warp_rigid
from core.models.flow3d import Flow3D, downsample_flow, upsample_flow
from core.models.flow_synthetic import MOTION_RANGES, rigid_flow, sample_motions
from core.models.registry import build_module
from core.tasks.flow import smoothness

GRID = GridConfig(xmin=-8, xmax=8, ymin=-4, ymax=4, zmin=-8, zmax=8, Z=16, Y=8, X=16)


def _linear_volume() -> torch.Tensor:
    """Channels x, y, z of each voxel's own mem coordinate: trilinear sampling reproduces it exactly."""
    c = voxel_centers_mem(GRID).reshape(GRID.Z, GRID.Y, GRID.X, 3)  # Z×Y×X×3
    return c.permute(3, 0, 1, 2)[None]  # 1×3×Z×Y×X


def test_rigid_flow_points_where_the_content_went():
    motion = se3.from_rt(se3.yaw_to_matrix(torch.tensor([math.radians(5.0)])), torch.tensor([[1.0, 0.0, -0.5]]))
    vol0 = _linear_volume()
    vol1 = warp_rigid(vol0, se3.invert(motion), GRID)  # the scene after the motion
    flow = rigid_flow(motion, GRID)
    back = warp_flow(vol1, flow)  # vol1(p + flow(p)) == vol0(p) where p + flow(p) stays inside
    p = voxel_centers_mem(GRID).reshape(GRID.Z, GRID.Y, GRID.X, 3)  # Z×Y×X×3
    q = p + flow[0].permute(1, 2, 3, 0)  # where each voxel's content went
    hi = torch.tensor([GRID.X - 1.0, GRID.Y - 1.0, GRID.Z - 1.0])
    # keep voxels whose interpolation stencils stay clear of the zero padding on both sides
    inside = (p >= 2).all(-1) & (p <= hi - 2).all(-1) & (q >= 1).all(-1) & (q <= hi - 1).all(-1)
    assert inside.sum() > 100
    torch.testing.assert_close(back[0][:, inside], vol0[0][:, inside], atol=1e-3, rtol=0)
    # a pure 1 m translation along x is exactly one voxel of +x flow everywhere
    shift = rigid_flow(se3.from_rt(torch.eye(3)[None], torch.tensor([[1.0, 0.0, 0.0]])), GRID)
    torch.testing.assert_close(shift[0, 0], torch.ones(GRID.Z, GRID.Y, GRID.X))
    assert shift[0, 1:].abs().max() < 1e-5


def test_sample_motions_thirds_and_ranges():
    M, kinds = sample_motions(9, generator=torch.Generator().manual_seed(0))
    assert sorted(kinds) == sorted(["large", "small", "zero"] * 3)
    for T, kind in zip(M, kinds):
        deg, metres = MOTION_RANGES[kind]
        assert float(T[:3, 3].abs().max()) <= metres + 1e-6
        assert math.degrees(float(se3.rotation_angle(T[:3, :3]))) <= math.sqrt(3) * deg + 1e-4
    torch.testing.assert_close(M[[k == "zero" for k in kinds]], torch.eye(4).expand(3, 4, 4))


def test_flow_up_and_down_sampling_scale_values():
    flow = torch.zeros(1, 3, 4, 2, 4)
    flow[:, 0] = 1.0  # one coarse voxel along x
    flow[:, 2] = -2.0
    up = upsample_flow(flow, (8, 4, 8))
    torch.testing.assert_close(up[:, 0], torch.full((1, 8, 4, 8), 2.0))
    torch.testing.assert_close(up[:, 2], torch.full((1, 8, 4, 8), -4.0))
    torch.testing.assert_close(downsample_flow(up, (4, 2, 4)), flow)


def test_flow_module_shapes_zero_init_and_config():
    net = Flow3D(in_channels=4, channels=4, levels=3, hidden=8)
    f = torch.randn(2, 4, 16, 8, 16)
    out = net(f, f)
    assert out["flow"].shape == (2, 3, 16, 8, 16)
    assert [tuple(l.shape[-3:]) for l in out["levels"]] == [(2, 1, 2), (4, 2, 4), (8, 4, 8)]
    assert out["flow"].abs().max() == 0  # zero-initialised last layers: zero motion before training
    assert build_module("flow3d", net.config()).config() == net.config()


def test_smoothness_hand_case():
    flow = torch.zeros(1, 3, 2, 2, 2)
    flow[..., 1] = 1.0  # a step of 1 along x only: mean |dx| = 1, dy = dz = 0
    assert abs(float(smoothness(flow)) - 1.0 / 3.0) < 1e-6


def test_object_motion_moves_only_the_block_and_its_flow_points_where_it_went():
    from core.models.flow_synthetic import move_block, sample_object_motions

    M, block = sample_object_motions(4, GRID, generator=torch.Generator().manual_seed(2))
    assert block.shape == (4, 1, GRID.Z, GRID.Y, GRID.X)
    frac = block.mean(dim=(1, 2, 3, 4))
    assert bool((frac > 0.0025).all()) and bool((frac < 0.04).all())  # object-sized blocks
    vol0 = _linear_volume().expand(4, 3, -1, -1, -1)
    vol1, flow = move_block(vol0, M, block, GRID)
    assert flow[block.expand_as(flow) == 0].abs().max() == 0  # static outside the block
    back = warp_flow(vol1, flow)
    # inside the block (landing spot inside the grid, clear of the padding): content found where it went
    p = voxel_centers_mem(GRID).reshape(1, GRID.Z, GRID.Y, GRID.X, 3)  # 1×Z×Y×X×3
    q = p + flow.permute(0, 2, 3, 4, 1)  # 4×Z×Y×X×3
    hi = torch.tensor([GRID.X - 1.0, GRID.Y - 1.0, GRID.Z - 1.0])
    landed = (warp_rigid(block, se3.invert(M), GRID) > 0.5).float()  # where the block's content is at t+1
    stencil_landed = warp_flow(landed, flow)[:, 0] > 1 - 1e-6  # every interpolation neighbour of p+flow landed
    ok = (block[:, 0] > 0) & stencil_landed & (q >= 1).all(-1) & (q <= hi - 1).all(-1)
    assert ok.sum() > 10
    torch.testing.assert_close(back.permute(0, 2, 3, 4, 1)[ok], vol0.permute(0, 2, 3, 4, 1)[ok], atol=1e-3, rtol=0)
    # the block's motion turns about its own centre: its mean flow is close to the pure translation
    assert float(flow.abs().max()) < 1.5 / GRID.voxel_size * 1.2 + 1.0


def test_kept_encoding_of_the_first_volume_gives_the_same_flow():
    """Flow3D(f0, f1, encoded0=encode(f0)) — a stream encodes each frame once — equals the plain call."""
    torch.manual_seed(0)
    net = Flow3D(in_channels=4, channels=6, levels=2, hidden=8, unit_cost=True, refine=True, soft_argmax=True).eval()
    with torch.no_grad():
        for p in net.parameters():
            if p.dim() > 1 and not p.any():
                p.normal_(std=0.3)
        f0, f1 = torch.randn(1, 4, 8, 4, 8), torch.randn(1, 4, 8, 4, 8)
        plain = net(f0, f1)["flow"]
        kept = net(f0, f1, encoded0=net.encode(f0))["flow"]
    assert plain.abs().max() > 0.05
    torch.testing.assert_close(kept, plain, atol=1e-5, rtol=1e-5)


def test_pyramid_levels_are_block_means_of_the_grid():
    """pool_pyramid against adaptive pooling of the finest level (the reference), for even and odd sizes."""
    from core.models.flow3d import level_sizes, pool_pyramid
    g = torch.Generator().manual_seed(1)
    for size in ((16, 4, 16), (9, 3, 10)):
        c = torch.randn(2, 3, *size, generator=g)
        sizes = level_sizes(size, 3)
        pyramid = pool_pyramid(c, sizes)
        assert [tuple(p.shape[-3:]) for p in pyramid] == [tuple(s) for s in sizes]
        for level, s in zip(pyramid, sizes):
            torch.testing.assert_close(level, torch.nn.functional.adaptive_avg_pool3d(c, s), atol=1e-6, rtol=1e-6)


def test_vacated_block_is_emptied_and_the_landing_place_holds_the_content():
    """move_block(vacate=True): what the block left is zero (an input volume: no points, mid grey);
    without it the old content stays (a feature map's occluded background)."""
    from core.models.flow_synthetic import move_block

    vol0 = torch.ones(1, 2, GRID.Z, GRID.Y, GRID.X)
    block = torch.zeros(1, 1, GRID.Z, GRID.Y, GRID.X)
    block[..., 2:4, :, 2:4] = 1.0
    shift = torch.eye(4).unsqueeze(0)
    shift[0, 0, 3] = 3 * GRID.voxel_size  # 3 voxels along x: the block leaves its old place entirely
    kept, _ = move_block(vol0, shift, block, GRID)
    emptied, flow = move_block(vol0, shift, block, GRID, vacate=True)
    assert float(kept.min()) == 1.0
    assert float(emptied[..., 2:4, :, 2:4].abs().max()) == 0.0  # vacated
    assert float(emptied[..., 2:4, :, 5:7].min()) > 0.99  # landed
    torch.testing.assert_close(emptied[..., 6:, :, :], vol0[..., 6:, :, :])  # elsewhere untouched
    assert float(flow[0, 0, 2, 0, 2]) == pytest.approx(3.0, abs=1e-5)
