"""Sub-voxel egomotion refinement (core.models.egomotion_refine) against slow obvious references."""

import pytest
import torch

from core.eval.egomotion_metrics import relative_pose_errors
from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref, voxel_centers_ref
from core.geometry.resample import sample_volume
from core.geometry.splat import splat_points
from core.geometry.voxelize import voxelize
from core.models.egomotion import EgomotionNet
from core.models.egomotion_refine import (DEFAULT_INFERENCE_LEVELS, FeatureMetricRefiner, alignment_jacobian, gauss_newton_refine,
                                          gaussian_blur3d, interior_mask, spatial_gradient)
from core.models.registry import build_module

GRID = GridConfig(xmin=-3, xmax=3, ymin=-1.5, ymax=1.5, zmin=-3, zmax=3, Z=12, Y=6, X=12)  # 0.5 m voxels
D = torch.float64


def _blobs(seed: int, channels: int = 2, n: int = 10):
    g = torch.Generator().manual_seed(seed)
    centres = (torch.rand(n, 3, generator=g, dtype=D) * 2 - 1) * torch.tensor([2.0, 0.8, 2.0], dtype=D)
    chan = torch.arange(n) % channels

    def field(pts: torch.Tensor) -> torch.Tensor:  # N×3 -> C×N: sums of Gaussians, σ = 0.6 m
        d2 = ((pts[:, None] - centres[None]) ** 2).sum(-1)
        k = torch.exp(-d2 / (2 * 0.6 ** 2))
        return torch.stack([k[:, chan == c].sum(1) for c in range(channels)])
    return field


def _volume(field, grid: GridConfig, a_T_b: torch.Tensor | None = None) -> torch.Tensor:
    """field sampled at the voxel centres p (or at a_T_b · p): 1×C×Z×Y×X."""
    p = voxel_centers_ref(grid, dtype=D)
    if a_T_b is not None:
        p = se3.apply(a_T_b[0], p)
    return field(p).reshape(1, -1, *grid.shape_zyx)


def _pose(rot, t) -> torch.Tensor:
    return se3.from_rt(se3.axis_angle_to_matrix(torch.tensor([rot], dtype=D)), torch.tensor([t], dtype=D))


def test_spatial_gradient_matches_the_loop_reference():
    vol = torch.randn(1, 2, 4, 3, 5, dtype=D, generator=torch.Generator().manual_seed(0))
    fast = spatial_gradient(vol, 0.5)
    slow = torch.zeros_like(fast)
    _, C, Z, Y, X = vol.shape
    for c in range(C):
        for z in range(Z):
            for y in range(Y):
                for x in range(X):
                    for axis, (n, idx) in enumerate(((X, x), (Y, y), (Z, z))):
                        lo, hi = max(idx - 1, 0), min(idx + 1, n - 1)
                        at = lambda i: vol[0, c, *(((z, y, i), (z, i, x), (i, y, x))[axis])]
                        slow[0, c, axis, z, y, x] = (at(hi) - at(lo)) / ((hi - lo) * 0.5)
    torch.testing.assert_close(fast, slow)


def test_jacobian_matches_finite_differences_of_the_trilinear_reference():
    # J(p) is d/dδ of R(exp(δ)·p) at δ = 0, R sampled trilinearly: central finite differences of that
    # sampling at interior voxel centres must equal the analytic p × ∇R | ∇R (up to O(ε): the second-order
    # move of a rotation crosses the trilinear kink at the voxel centre).
    ref = _volume(_blobs(1), GRID)
    J = alignment_jacobian(ref, GRID)  # 1×C×N×6
    p = voxel_centers_ref(GRID, dtype=D)
    mem_T = mem_T_ref(GRID, dtype=D)
    eps = 1e-6
    fd = torch.zeros_like(J)
    for i in range(6):
        d = torch.zeros(1, 6, dtype=D)
        d[0, i] = eps
        samples = []
        for sign in (1.0, -1.0):
            T = se3.from_rt(se3.axis_angle_to_matrix(sign * d[:, :3]), sign * d[:, 3:])
            mem = se3.apply(mem_T @ T[0], p)[None]  # 1×N×3
            samples.append(sample_volume(ref, mem))  # 1×C×N
        fd[..., i] = (samples[0] - samples[1]) / (2 * eps)
    inside = interior_mask(GRID, dtype=D).reshape(-1).bool()
    torch.testing.assert_close(J[:, :, inside], fd[:, :, inside], atol=1e-5, rtol=1e-5)
    # and the voxel-subset form is the same Jacobian
    index = torch.tensor([5, 77, 300])
    torch.testing.assert_close(alignment_jacobian(ref, GRID, index), J[:, :, index])


def test_gauss_newton_step_matches_a_least_squares_step_on_finite_differences():
    field = _blobs(2)
    gt = _pose([0.01, -0.02, 0.015], [0.12, -0.05, 0.2])
    ref, query = _volume(field, GRID), _volume(field, GRID, gt)  # query(p) = ref(gt·p): ref0_T_ref1 = gt
    start = _pose([0.0, 0.005, 0.0], [0.05, 0.0, 0.1])
    E, _ = gauss_newton_refine(ref, query, start, GRID, iterations=1, damping=0.0)
    # slow step: residual r = Q_E(p) − R(p) over the voxels that stay inside, Jacobian by finite differences
    p = voxel_centers_ref(GRID, dtype=D)
    mem_T = mem_T_ref(GRID, dtype=D)
    warped = sample_volume(query, se3.apply(mem_T @ se3.invert(start)[0], p)[None])[0]  # C×N
    inner = interior_mask(GRID, dtype=D).reshape(-1).bool()
    moved = se3.apply(mem_T @ se3.invert(start)[0], p)
    lo, hi = torch.ones(3, dtype=D), torch.tensor([GRID.X - 2, GRID.Y - 2, GRID.Z - 2], dtype=D)
    keep = inner & ((moved >= lo) & (moved <= hi)).all(1)
    r = (warped - ref.reshape(ref.shape[1], -1))[:, keep].reshape(-1)
    cols = []
    for i in range(6):
        d = torch.zeros(1, 6, dtype=D)
        d[0, i] = 1e-5
        vals = [sample_volume(ref, se3.apply(mem_T @ se3.from_rt(se3.axis_angle_to_matrix(s * d[:, :3]),
                                                                  s * d[:, 3:])[0], p)[None])[0]
                for s in (1.0, -1.0)]
        cols.append(((vals[0] - vals[1]) / 2e-5)[:, keep].reshape(-1))
    delta = torch.linalg.lstsq(torch.stack(cols, 1), r[:, None]).solution[:, 0]
    expected = se3.from_rt(se3.axis_angle_to_matrix(delta[None, :3]), delta[None, 3:]) @ start
    torch.testing.assert_close(E, expected, atol=1e-6, rtol=1e-5)


def test_gauss_newton_recovers_a_known_sub_voxel_motion():
    field = _blobs(3)
    gt = _pose([0.0, 0.03, 0.0], [0.13, -0.04, -0.21])  # 0.26 / 0.08 / 0.42 voxel, 1.7° yaw
    ref, query = _volume(field, GRID), _volume(field, GRID, gt)
    E, history = gauss_newton_refine(ref, query, torch.eye(4, dtype=D)[None], GRID, iterations=6)
    err = relative_pose_errors(E, gt)
    # translation to 1/40 of a voxel; rotation to ~0.5°: on a grid this small (6 m across) trilinear
    # interpolation biases the optimum by ~0.009 rad whatever the motion (0.0089 with no rotation at all)
    assert float(err["trans_err_m"][0]) < 0.0125
    assert float(err["rot_err_rad"][0]) < 0.015
    assert len(history) == 6
    # identical volumes: the identity is a fixed point
    E0, _ = gauss_newton_refine(ref, ref, torch.eye(4, dtype=D)[None], GRID, iterations=2)
    torch.testing.assert_close(E0, torch.eye(4, dtype=D)[None], atol=1e-9, rtol=0)


def test_splatted_points_give_sub_voxel_motion_where_binary_occupancy_cannot():
    # Points on six spheres (r 0.6 m); the query is the same points seen from a frame moved by under half
    # a voxel (and 1.1° of yaw). Splatted, the alignment recovers it; binary occupancy (nearest voxel) has
    # no sub-voxel information and lands several times farther off.
    g = torch.Generator().manual_seed(0)
    centres = (torch.rand(6, 3, generator=g, dtype=D) * 2 - 1) * torch.tensor([1.8, 0.4, 1.8], dtype=D)
    dirs = torch.randn(6, 500, 3, generator=g, dtype=D)
    pts = (centres[:, None] + 0.6 * dirs / dirs.norm(dim=-1, keepdim=True)).reshape(1, -1, 3)  # in ref0
    gt = _pose([0.0, 0.02, 0.0], [0.15, 0.05, -0.12])  # ref0_T_ref1
    pts1 = se3.apply(se3.invert(gt), pts)  # the same points in ref1
    errs = {}
    for name, make in (("splat", lambda q: splat_points(q, GRID)), ("binary", lambda q: voxelize(q, GRID))):
        r, q = gaussian_blur3d(make(pts).to(D), 0.7), gaussian_blur3d(make(pts1).to(D), 0.7)
        E, _ = gauss_newton_refine(r, q, torch.eye(4, dtype=D)[None], GRID, iterations=8)
        errs[name] = relative_pose_errors(E, gt)
    assert float(errs["splat"]["trans_err_m"][0]) < 0.025  # of 0.20 m (measured 0.017)
    assert float(errs["splat"]["rot_err_rad"][0]) < 0.006  # of 0.02 rad (measured 0.0033)
    assert float(errs["binary"]["trans_err_m"][0]) > 2 * float(errs["splat"]["trans_err_m"][0])
    assert float(errs["binary"]["rot_err_rad"][0]) > 5 * float(errs["splat"]["rot_err_rad"][0])


def test_gaussian_blur_matches_a_dense_3d_kernel():
    vol = torch.randn(1, 2, 5, 4, 6, dtype=D, generator=torch.Generator().manual_seed(5))
    sigma = 0.8
    r = max(1, round(2 * sigma))
    x = torch.arange(-r, r + 1, dtype=D)
    k1 = torch.exp(-0.5 * (x / sigma) ** 2)
    k1 = k1 / k1.sum()
    k3 = k1[:, None, None] * k1[None, :, None] * k1[None, None, :]
    slow = torch.nn.functional.conv3d(vol.reshape(2, 1, 5, 4, 6), k3[None, None], padding=r).reshape(vol.shape)
    torch.testing.assert_close(gaussian_blur3d(vol, sigma), slow)
    assert gaussian_blur3d(vol, 0.0) is vol


def test_refiner_starts_as_geometric_alignment_and_learns_through_the_solve():
    field = _blobs(6, channels=1)
    gt = _pose([0.0, 0.02, 0.0], [0.1, 0.0, -0.15])
    ref_in = torch.cat([_volume(field, GRID), torch.zeros(1, 3, *GRID.shape_zyx, dtype=D)], 1)
    query_in = torch.cat([_volume(field, GRID, gt), torch.zeros(1, 3, *GRID.shape_zyx, dtype=D)], 1)
    feats = torch.randn(2, 3, *GRID.shape_zyx, dtype=D, generator=torch.Generator().manual_seed(7))
    start = torch.eye(4, dtype=D)[None]
    # untrained and without learned channels: confidence exactly 1, i.e. the plain solve of the occupancy
    refiner = FeatureMetricRefiner(feature_dim=3, levels=((1.0, 0.1, 1), (0.7, 0.0, 2))).double()
    E, steps = refiner(ref_in, query_in, feats[:1], feats[1:], start, GRID)
    assert len(steps) == 3
    plain = start
    for sigma, robust, n in ((1.0, 0.1, 1), (0.7, 0.0, 2)):
        plain, _ = gauss_newton_refine(gaussian_blur3d(ref_in[:, :1], sigma), gaussian_blur3d(query_in[:, :1], sigma),
                                       plain, GRID, iterations=n, robust_scale=robust, max_step=refiner.max_step)
    torch.testing.assert_close(E, plain)
    # with learned channels, the pose loss reaches the gain, the projection and the confidence through the solve
    refiner = FeatureMetricRefiner(feature_dim=3, learned_channels=2, levels=((0.7, 0.0, 2),)).double()
    E, _ = refiner(ref_in, query_in, feats[:1], feats[1:], start, GRID)
    (E[:, :3, 3] - gt[:, :3, 3]).abs().sum().backward()
    for p in (refiner.gain, refiner.project.weight, refiner.confidence.weight):
        assert p.grad is not None and float(p.grad.abs().sum()) > 0
    with pytest.raises(ValueError):
        FeatureMetricRefiner(feature_dim=3, levels=((1.0, 0.0, 0),))


def test_refiner_runs_its_inference_levels_in_eval_mode_and_its_training_levels_in_train_mode():
    field = _blobs(9, channels=1)
    gt = _pose([0.0, 0.015, 0.0], [0.12, 0.0, 0.1])
    ref_in = torch.cat([_volume(field, GRID), torch.zeros(1, 3, *GRID.shape_zyx, dtype=D)], 1)
    query_in = torch.cat([_volume(field, GRID, gt), torch.zeros(1, 3, *GRID.shape_zyx, dtype=D)], 1)
    feats = torch.randn(2, 3, *GRID.shape_zyx, dtype=D, generator=torch.Generator().manual_seed(3))
    start = torch.eye(4, dtype=D)[None]
    train_levels, eval_levels = ((1.0, 0.1, 1), (0.7, 0.0, 1)), ((1.0, 0.1, 1), (0.7, 0.0, 4))
    refiner = FeatureMetricRefiner(feature_dim=3, levels=train_levels, inference_levels=eval_levels).double()

    def plain(levels):
        E = start
        for sigma, robust, n in levels:
            E, _ = gauss_newton_refine(gaussian_blur3d(ref_in[:, :1], sigma), gaussian_blur3d(query_in[:, :1], sigma),
                                       E, GRID, iterations=n, robust_scale=robust, max_step=refiner.max_step)
        return E

    E_train, steps_train = refiner.train()(ref_in, query_in, feats[:1], feats[1:], start, GRID)
    E_eval, steps_eval = refiner.eval()(ref_in, query_in, feats[:1], feats[1:], start, GRID)
    assert (len(steps_train), len(steps_eval)) == (2, 5)
    torch.testing.assert_close(E_train, plain(train_levels))
    torch.testing.assert_close(E_eval, plain(eval_levels))
    assert not torch.allclose(E_eval, E_train)
    rebuilt = FeatureMetricRefiner(feature_dim=3, **refiner.config())
    assert rebuilt.inference_levels == eval_levels and rebuilt.levels == train_levels
    old = refiner.config()
    del old["inference_levels"]  # a bundle saved before the option: the default schedule at inference
    assert FeatureMetricRefiner(feature_dim=3, **old).inference_levels == DEFAULT_INFERENCE_LEVELS
    with pytest.raises(ValueError, match="inference_levels need at least one iteration"):
        FeatureMetricRefiner(feature_dim=3, inference_levels=())


def test_module_with_refinement_rebuilds_and_old_configs_load_without_it():
    g = GridConfig(xmin=-8, xmax=8, ymin=-2, ymax=2, zmin=-8, zmax=8, Z=16, Y=4, X=16)
    net = EgomotionNet(grid=g, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8, input_occupancy="splat",
                       refine={"levels": [[1.0, 0.1, 2]]})
    x = torch.rand(1, 4, 16, 4, 16, generator=torch.Generator().manual_seed(8))
    out = net(x, x)
    assert out["refine_steps"].shape == (2, 1, 4, 4)
    torch.testing.assert_close(out["ref0_T_ref1"], out["refine_steps"][-1])
    clone = build_module("egomotion", net.config())
    assert clone.config() == net.config()
    clone.load_state_dict(net.state_dict())
    old = net.config()
    del old["input_occupancy"], old["refine"]  # a bundle saved before these options
    legacy = build_module("egomotion", old)
    assert legacy.refiner is None and legacy.input_occupancy == "binary"
    assert "refine_steps" not in legacy(x, x)
    with pytest.raises(ValueError):
        EgomotionNet(grid=g, input_occupancy="dense")
