"""Egomotion module: inverse-compositional warping (always the ORIGINAL query), shapes, loss, task smoke."""

import math

import pytest
import torch

from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_rigid
from core.models.egomotion import EgomotionNet, pool_to, pose_loss
from core.models.registry import build_module

GRID = GridConfig(xmin=-8, xmax=8, ymin=-2, ymax=2, zmin=-8, zmax=8, Z=16, Y=4, X=16)


def _smooth_volume(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(1, 2, 16, 4, 16, generator=g)
    for _ in range(3):
        v = torch.nn.functional.avg_pool3d(v, 3, 1, 1, count_include_pad=False)
    return v


def _pose(deg: float, t) -> torch.Tensor:
    return se3.from_rt(se3.yaw_to_matrix(torch.tensor([math.radians(deg)])), torch.tensor([t], dtype=torch.float32))


def test_two_warps_equal_one_warp_by_composition():
    # vol_a = warp(vol_b, b_T_a); vol_c = warp(vol_a, a_T_c) == warp(vol_b, b_T_a · a_T_c) (interior,
    # up to the second interpolation, which is what inverse composition avoids).
    vol = _smooth_volume(0)
    b_T_a, a_T_c = _pose(3.0, (0.3, 0.0, -0.2)), _pose(-2.0, (0.4, 0.0, 0.5))
    twice = warp_rigid(warp_rigid(vol, b_T_a, GRID), a_T_c, GRID)
    once = warp_rigid(vol, b_T_a @ a_T_c, GRID)
    inner = (..., slice(3, -3), slice(None), slice(3, -3))
    assert (twice[inner] - once[inner]).abs().max() < 0.1 * vol.abs().max()
    # and the identity composition is exact
    torch.testing.assert_close(warp_rigid(vol, torch.eye(4)[None], GRID), vol)


def test_module_warps_the_original_query_by_the_composed_estimate(monkeypatch):
    torch.manual_seed(0)
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, scales=(0.5, 1.0), rotation_counts=(1, 3, 1),
                       radius=(1, 1, 1), hidden=16).eval()
    for head in net.heads:  # non-zero updates so the estimate changes between scales
        torch.nn.init.normal_(head[-1].weight, std=0.05)
    ref_in, query_in = torch.randn(1, 4, 16, 4, 16), torch.randn(1, 4, 16, 4, 16)
    calls = []
    original = EgomotionNet.warp_query

    def spy(self, query, ref0_T_ref1, grid):
        calls.append((query.detach().clone(), ref0_T_ref1.detach().clone(), grid))
        return original(self, query, ref0_T_ref1, grid)

    monkeypatch.setattr(EgomotionNet, "warp_query", spy)
    with torch.no_grad():
        out = net(ref_in, query_in)
        query_feat = net.encoder(query_in)
    assert len(calls) == 2  # one batched warp of all candidates per scale
    R = 3
    for i, (query, transforms, grid) in enumerate(calls):
        expected_query = pool_to(query_feat, grid).expand(R, -1, -1, -1, -1)
        torch.testing.assert_close(query, expected_query)  # the ORIGINAL (pooled) query, never a warp
        estimate_in = torch.eye(4)[None] if i == 0 else out["per_scale"][0]
        candidates = getattr(net, f"candidates_{i}")
        torch.testing.assert_close(transforms, candidates @ estimate_in.expand(R, 4, 4), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(out["per_scale"][0], torch.eye(4)[None])
    assert bool(se3.is_rigid(out["ref0_T_ref1"], tol=1e-4).all())


def test_untrained_module_predicts_identity_and_rebuilds_from_config():
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8)
    x = torch.randn(2, 4, 16, 4, 16)
    out = net(x, x)
    assert out["per_scale"].shape == (2, 2, 4, 4)
    torch.testing.assert_close(out["ref0_T_ref1"], torch.eye(4).expand(2, 4, 4))
    clone = build_module("egomotion", net.config())
    assert clone.config() == net.config()


def test_pose_loss_hand_case():
    gt = _pose(0.0, (1.0, 0.0, 0.0))
    est = _pose(math.degrees(0.1), (1.0, 0.5, 0.0))
    loss = pose_loss(est, gt, rotation_weight=1.0)
    # chordal ‖R_e − R_g‖_F/√2 = 2 sin(θ/2) for a rotation by θ
    assert float(loss["rotation"]) == pytest.approx(2 * math.sin(0.05), abs=1e-5)
    assert float(loss["translation"]) == pytest.approx(0.5, abs=1e-6)
