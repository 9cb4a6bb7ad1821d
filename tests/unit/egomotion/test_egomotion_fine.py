"""The egomotion module's fine stage (core/models/egomotion_fine.py): its volume against a per-view loop,
its alignment against a plain Gauss-Newton loop, and where the module runs it (eval only, configs)."""

import pytest
import torch

from core.geometry.camera import intrinsics
from core.geometry.grid import GridConfig
from core.geometry.splat import surface_splat
from core.models.egomotion import DEFAULT_FINE_ALIGNMENT, EgomotionNet
from core.models.egomotion_fine import FineAlignment, align_fine, fine_grid, fine_occupancy
from core.models.egomotion_inputs import egomotion_fine_volume
from core.models.egomotion_refine import gauss_newton_refine, gaussian_blur3d
from core.models.registry import build_module
from tests.unit.egomotion.test_egomotion_refine import GRID, _blobs, _pose, _volume

D = torch.float64


def _views(B: int = 2, V: int = 3, H: int = 6, W: int = 8):
    g = torch.Generator().manual_seed(4)
    depth = 1.0 + 2.0 * torch.rand(B, V, H, W, generator=g)
    depth[0, 1, 2, 3] = 0.0  # a missing pixel
    pix = intrinsics(4.0, 4.0, W / 2, H / 2).expand(B, V, 4, 4).clone()
    cam = torch.stack([_pose([0.0, 0.3 * v, 0.0], [0.2 * v, 0.1, -0.5]).float()[0] for v in range(V)])  # V×4×4
    return depth, pix, cam.expand(B, V, 4, 4).clone()


def test_fine_volume_is_the_clamped_max_over_views_of_each_views_splat():
    from core.geometry.camera import depth_to_points

    depth, pix, cam = _views()
    grid = fine_grid(GRID, 2)
    assert grid.shape_zyx == (24, 12, 24) and grid.voxel_size == pytest.approx(GRID.voxel_size / 2)
    got = fine_occupancy(depth, pix, cam, grid)
    B, V = depth.shape[:2]
    for b in range(B):
        expected = None
        for v in range(V):  # slow and obvious: one view at a time, then the max, then the clamp
            xyz, valid = depth_to_points(depth[b, v][None], pix[b, v][None])
            one = surface_splat(xyz, valid, pix[b, v][None], cam[b, v][None], grid)[0]  # 1×Z×Y×X
            expected = one if expected is None else torch.maximum(expected, one)
        torch.testing.assert_close(got[b], expected.clamp(max=1.0))
    assert float(got.amax()) <= 1.0 and float(got.sum()) > 0


def test_align_fine_runs_its_levels_from_the_estimate():
    field = _blobs(5, channels=1)
    grid = fine_grid(GRID, 2)
    gt = _pose([0.0, 0.01, 0.0], [0.06, 0.0, -0.04])
    reference, query = _volume(field, grid), _volume(field, grid, gt)
    start = _pose([0.0, 0.012, 0.0], [0.1, 0.0, 0.0])
    config = FineAlignment(levels=((1.0, 0.1, 2), (0.7, 0.0, 3)))
    E = align_fine(start, reference, query, grid, config)
    slow = start
    for sigma, robust, n in config.levels:
        slow, _ = gauss_newton_refine(gaussian_blur3d(reference, sigma), gaussian_blur3d(query, sigma), slow, grid,
                                      iterations=n, damping=config.damping, robust_scale=robust,
                                      max_step=config.max_step)
    torch.testing.assert_close(E, slow)
    assert float((E[:, :3, 3] - gt[:, :3, 3]).norm()) < float((start[:, :3, 3] - gt[:, :3, 3]).norm())


def test_fine_alignment_config_round_trips_and_refuses_nonsense():
    config = FineAlignment(**{"factor": 3, "levels": [[0.7, 0.1, 4]], "damping": 0.01, "max_step": [0.1, 2.0]})
    assert FineAlignment(**config.to_dict()) == config
    for bad in ({"factor": 0}, {"levels": []}, {"levels": [[0.7, 0.1, 0]]}):
        with pytest.raises(ValueError, match="FineAlignment"):
            FineAlignment(**bad)


def _net(**kw) -> EgomotionNet:
    g = GridConfig(xmin=-8, xmax=8, ymin=-2, ymax=2, zmin=-8, zmax=8, Z=16, Y=4, X=16)
    base = dict(grid=g, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8, input_occupancy="splat",
                refine={"levels": [[1.0, 0.1, 1]]})
    return EgomotionNet(**{**base, **kw})


def test_the_module_runs_its_fine_stage_in_eval_mode_only_and_keeps_it_in_its_config():
    net = _net()
    assert net.fine == FineAlignment(**DEFAULT_FINE_ALIGNMENT) and net.fine_grid.shape_zyx == (32, 8, 32)
    depth, pix, cam = _views(B=1, V=2)
    E = _pose([0.0, 0.01, 0.0], [0.3, 0.0, 0.2]).float()
    net.eval()
    fine0 = egomotion_fine_volume(net, depth, pix, cam)
    assert fine0.shape == (1, 1, 32, 8, 32)
    moved = net.refine_fine(E, fine0, fine0)  # the same frame twice: the stage pulls towards the identity
    assert float(moved[:, :3, 3].norm()) < float(E[:, :3, 3].norm())
    assert net.refine_fine(E, None, None) is E
    net.train()
    assert egomotion_fine_volume(net, depth, pix, cam) is None and net.refine_fine(E, fine0, fine0) is E
    # configs: saved and rebuilt; a config of a bundle saved before the option gets the default
    clone = build_module("egomotion", net.config())
    assert clone.config() == net.config()
    legacy = net.config()
    del legacy["fine_alignment"]
    assert build_module("egomotion", legacy).fine == net.fine
    # without the sub-voxel stage, or on binary occupancy, or switched off: no fine stage
    assert _net(refine=None).fine is None and _net(input_occupancy="binary").fine is None
    off = _net(fine_alignment=None)
    assert off.fine is None and off.config()["fine_alignment"] is None and off.fine_grid is None
