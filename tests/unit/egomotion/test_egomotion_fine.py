"""The egomotion module's fine stage (core/models/egomotion_fine.py): its splat volume against a per-view loop,
its splat alignment against a plain Gauss-Newton loop, its TSDF alignment on a hand-built room whose motion is
known, and where the module runs it (eval only, configs)."""

import pytest
import torch

from core.geometry.camera import intrinsics
from core.geometry.grid import GridConfig
from core.geometry.splat import surface_splat
from core.models.egomotion import DEFAULT_FINE_ALIGNMENT, EgomotionNet
from core.geometry import se3
from core.models.egomotion_fine import FineAlignment, FineFrame, align_fine, fine_frame, fine_grid, fine_occupancy
from core.models.egomotion_inputs import egomotion_fine_frame
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
    # a stage saved before kinds existed (no "kind") is the splat stage it was
    config = FineAlignment(**{"factor": 3, "levels": [[0.7, 0.1, 4]], "damping": 0.01, "max_step": [0.1, 2.0]})
    assert config.kind == "splat" and FineAlignment(**config.to_dict()) == config
    tsdf = FineAlignment(**DEFAULT_FINE_ALIGNMENT)
    assert (tsdf.kind, tsdf.factor) == ("tsdf", 4) and FineAlignment(**tsdf.to_dict()) == tsdf
    for bad in ({"factor": 0}, {"levels": []}, {"levels": [[0.7, 0.1, 0]]}, {"kind": "icp"}, {"iterations": 0},
                {"truncation": 0.0}, {"robust": -1.0}, {"point_cell": 0.0}):
        with pytest.raises(ValueError, match="FineAlignment"):
            FineAlignment(**bad)


ROOM = GridConfig(xmin=-3.0, xmax=3.0, ymin=-1.5, ymax=1.5, zmin=-1.0, zmax=5.0, Z=12, Y=6, X=12)
# Planes n·x = c in ref0 (Y down): the floor, the back wall, a side wall and a tilted panel, so that every
# direction of motion changes some plane's distance.
PLANES = [((0.0, 1.0, 0.0), 0.8), ((0.0, 0.0, 1.0), 3.6), ((1.0, 0.0, 0.0), -1.7), ((0.6, 0.0, 0.8), 2.6)]


def _room_depth(ref0_T_cam: torch.Tensor, H: int = 96, W: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth (1×1×H×W) a pinhole camera at `ref0_T_cam` (4×4) sees of PLANES: per pixel, the nearest
    plane its ray meets in front of the camera (ray-plane intersection, by hand); and its pix_T_cam."""
    fx = fy = 60.0
    cx, cy = (W - 1) / 2, (H - 1) / 2
    v, u = torch.meshgrid(torch.arange(H, dtype=D), torch.arange(W, dtype=D), indexing="ij")
    ray = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)  # H×W×3, z = 1: t is the depth
    R, o = ref0_T_cam[:3, :3], ref0_T_cam[:3, 3]
    direction = ray @ R.T  # H×W×3 in ref0
    depth = torch.full((H, W), float("inf"), dtype=D)
    for n, c in PLANES:
        n = torch.tensor(n, dtype=D)
        denom = direction @ n
        t = (c - float(n @ o)) / denom
        depth = torch.where((denom.abs() > 1e-9) & (t > 0.1), torch.minimum(depth, t), depth)
    depth = torch.where(torch.isfinite(depth), depth, torch.zeros_like(depth))
    return depth[None, None], intrinsics(fx, fy, cx, cy).to(D)[None]


def test_tsdf_alignment_recovers_a_known_motion_in_a_hand_built_room():
    """Frame 0 sees the room from ref0's origin, frame 1 from `gt` = ref0_T_ref1 (each camera at its ref);
    from a start 0.6° and 0.25 m off, and from `gt` itself, the stage ends within 2e-3 rad and 5 mm of `gt`
    (what is left is the room's own bias: its creases, where bilinear depth cuts the corner, weigh more in
    a scene of four planes than in the synthetic world, where the stage ends where ICP does)."""
    gt = _pose([0.004, 0.012, -0.003], [0.12, 0.03, 0.25])[0]
    depth0, pix = _room_depth(torch.eye(4, dtype=D))
    depth1, _ = _room_depth(gt)
    cam_T_ref = torch.eye(4, dtype=D)[None, None]
    config = FineAlignment(**{**DEFAULT_FINE_ALIGNMENT, "point_cell": 0.25})
    f0 = fine_frame(depth0, pix, cam_T_ref, ROOM, config)
    f1 = fine_frame(depth1, pix, cam_T_ref, ROOM, config)
    assert f0.volume.shape == (1, 2, 48, 24, 48) and int(f1.points_valid.sum()) > 1000

    def error(T):
        delta = se3.invert(gt[None]) @ T[None]
        return float(se3.rotation_angle(delta[:, :3, :3])[0]), float(delta[0, :3, 3].norm())
    far = _pose([0.0, 0.01, 0.0], [0.15, 0.0, -0.2])[0] @ gt
    assert error(far)[0] > 0.009 and error(far)[1] > 0.2
    for start in (far, gt):
        E = align_fine(start[None], f0, f1, fine_grid(ROOM, config.factor), config)[0]
        assert error(E)[0] < 2e-3 and error(E)[1] < 0.005, error(E)


def test_tsdf_alignment_keeps_an_estimate_it_has_no_points_for():
    depth0, pix = _room_depth(torch.eye(4, dtype=D))
    config = FineAlignment(**DEFAULT_FINE_ALIGNMENT)
    f0 = fine_frame(depth0, pix, torch.eye(4, dtype=D)[None, None], ROOM, config)
    empty = FineFrame(f0.volume, f0.points, torch.zeros_like(f0.points_valid))
    start = _pose([0.0, 0.01, 0.0], [0.15, 0.0, -0.2])
    torch.testing.assert_close(align_fine(start, f0, empty, fine_grid(ROOM, config.factor), config), start)


def _net(**kw) -> EgomotionNet:
    g = GridConfig(xmin=-8, xmax=8, ymin=-2, ymax=2, zmin=-8, zmax=8, Z=16, Y=4, X=16)
    base = dict(grid=g, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8, input_occupancy="splat",
                refine={"levels": [[1.0, 0.1, 1]]})
    return EgomotionNet(**{**base, **kw})


def test_the_module_runs_its_fine_stage_in_eval_mode_only_and_keeps_it_in_its_config():
    net = _net()
    assert net.fine == FineAlignment(**DEFAULT_FINE_ALIGNMENT) and net.fine_grid.shape_zyx == (64, 16, 64)
    depth, pix = (t.float() for t in _room_depth(torch.eye(4, dtype=D)))
    cam = torch.eye(4)[None, None]
    E = _pose([0.0, 0.01, 0.0], [0.3, 0.0, 0.2]).float()
    net.eval()
    fine0 = egomotion_fine_frame(net, depth, pix, cam)
    assert fine0.volume.shape == (1, 2, 64, 16, 64) and fine0.points.shape[0] == 1
    moved = net.refine_fine(E, fine0, fine0)  # the same frame twice: the stage pulls towards the identity
    assert float(moved[:, :3, 3].norm()) < float(E[:, :3, 3].norm())
    assert net.refine_fine(E, None, None) is E
    net.train()
    assert egomotion_fine_frame(net, depth, pix, cam) is None and net.refine_fine(E, fine0, fine0) is E
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


def test_one_step_recovers_a_shift_along_a_walls_normal_exactly():
    """Against a wall's TSDF, which is linear along its normal inside the band, one Gauss-Newton step from an
    estimate 5 cm off along the normal lands on the truth: the Jacobian's translation part and the step's sign."""
    depth0, pix = _room_depth(torch.eye(4, dtype=D))
    flat = torch.full_like(depth0, 3.3)  # a fronto-parallel wall filling the image
    config = FineAlignment(**{**DEFAULT_FINE_ALIGNMENT, "iterations": 1, "robust": 1.0, "damping": 0.0})
    cam = torch.eye(4, dtype=D)[None, None]
    f0 = fine_frame(flat, pix, cam, ROOM, config)
    f1 = fine_frame(flat, pix, cam, ROOM, config)
    assert bool(f1.points_valid.any())
    start = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.05])
    E = align_fine(start, f0, f1, fine_grid(ROOM, config.factor), config)
    assert abs(float(E[0, 2, 3])) < 1e-6 and torch.allclose(E[0, :3, :3], torch.eye(3, dtype=D), atol=1e-9)


def test_a_tsdf_stage_needs_frame_0s_tsdf_and_frame_1s_points():
    depth0, pix = _room_depth(torch.eye(4, dtype=D))
    config = FineAlignment(**DEFAULT_FINE_ALIGNMENT)
    frame = fine_frame(depth0, pix, torch.eye(4, dtype=D)[None, None], ROOM, config)
    grid = fine_grid(ROOM, config.factor)
    points_only = FineFrame(None, frame.points, frame.points_valid)
    with pytest.raises(ValueError, match="TSDF stage needs"):
        align_fine(torch.eye(4, dtype=D)[None], points_only, points_only, grid, config)
    with pytest.raises(ValueError, match="TSDF stage needs"):  # bare tensors are splat volumes
        align_fine(torch.eye(4, dtype=D)[None], torch.zeros(1, 1, *grid.shape_zyx, dtype=D),
                   torch.zeros(1, 1, *grid.shape_zyx, dtype=D), grid, config)


def test_a_frames_parts_are_built_once_and_only_when_read(monkeypatch):
    """A pair reads frame 0's TSDF and frame 1's points: frame 1's TSDF (most of the cost) is never built;
    a part read twice is built once; the lazy frame aligns exactly as one built eagerly."""
    import core.models.egomotion_fine as fine

    calls = []
    real = fine.projective_tsdf
    monkeypatch.setattr(fine, "projective_tsdf", lambda *a, **k: calls.append(1) or real(*a, **k))
    gt = _pose([0.004, 0.012, -0.003], [0.12, 0.03, 0.25])[0]
    depth0, pix = _room_depth(torch.eye(4, dtype=D))
    depth1, _ = _room_depth(gt)
    cam = torch.eye(4, dtype=D)[None, None]
    config = FineAlignment(**DEFAULT_FINE_ALIGNMENT)
    f0, f1 = fine_frame(depth0, pix, cam, ROOM, config), fine_frame(depth1, pix, cam, ROOM, config)
    assert calls == []
    start = _pose([0.0, 0.004, 0.0], [0.05, 0.0, -0.05]) @ gt[None]
    E = align_fine(start, f0, f1, fine_grid(ROOM, config.factor), config)
    assert len(calls) == 1  # frame 0's TSDF only
    assert f0.volume is f0.volume and len(calls) == 1
    eager = FineFrame(f0.volume, f1.points, f1.points_valid)
    torch.testing.assert_close(align_fine(start, eager, eager, fine_grid(ROOM, config.factor), config), E)
