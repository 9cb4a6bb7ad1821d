"""Egomotion module: inverse-compositional warping (always the ORIGINAL query), shapes, loss, task smoke."""

import math

import pytest
import torch

from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_rigid
from core.eval.egomotion_metrics import relative_pose_errors
from core.models.egomotion import EgomotionNet, pool_to, pose_loss, se3_exp_update
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
    assert len(calls) == 2  # one warp of the query under all candidates per scale (batch 1)
    R = 3
    for i, (query, transforms, grid) in enumerate(calls):
        torch.testing.assert_close(query, pool_to(query_feat, grid))  # the ORIGINAL (pooled) query, never a warp
        estimate_in = torch.eye(4)[None] if i == 0 else out["per_scale"][0]
        candidates = getattr(net, f"candidates_{i}")
        torch.testing.assert_close(transforms, candidates @ estimate_in.expand(R, 4, 4), atol=1e-5, rtol=1e-5)
    assert not torch.allclose(out["per_scale"][0], torch.eye(4)[None])
    assert bool(se3.is_rigid(out["ref0_T_ref1"], tol=1e-4).all())


def test_untrained_module_predicts_identity_and_rebuilds_from_config():
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8, soft_argmax=False)
    x = torch.randn(2, 4, 16, 4, 16)
    out = net(x, x)
    assert out["per_scale"].shape == (2, 2, 4, 4)
    torch.testing.assert_close(out["ref0_T_ref1"], torch.eye(4).expand(2, 4, 4))
    clone = build_module("egomotion", net.config())
    assert clone.config() == net.config()
    # with the soft-argmax prior (the default) the same pair of identical inputs stays near identity
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8)
    out = net(x, x)
    err = relative_pose_errors(out["ref0_T_ref1"].detach(), torch.eye(4).expand(2, 4, 4))
    assert float(err["rot_err_deg"].max()) < 0.5 and float(err["trans_err_m"].max()) < 0.3
    assert build_module("egomotion", net.config()).config() == net.config()


def _slow_prior(net: EgomotionNet, scores: torch.Tensor, index: int, voxel: float) -> torch.Tensor:
    """Reference soft-argmax by explicit loops over (rotation, displacement)."""
    beta = float(net.log_beta[index].exp())
    angles = getattr(net, f"candidate_angles_{index}")
    disp = net.displacements
    R, D = angles.shape[0], disp.shape[0]
    out = []
    for b in range(scores.shape[0]):
        w = [math.exp(beta * float(scores[b, i * D + d])) for i in range(R) for d in range(D)]
        total = sum(w)
        omega, t = torch.zeros(3), torch.zeros(3)
        for i in range(R):
            for d in range(D):
                omega += w[i * D + d] / total * angles[i]
                t -= w[i * D + d] / total * disp[d] * voxel
        out.append(torch.cat([omega, t]))
    return torch.stack(out)


def test_soft_argmax_prior_matches_the_loop_reference_and_peaks():
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, scales=(0.5, 1.0), radius=(1, 1, 1), hidden=8)
    scores = torch.randn(2, 27 * 27, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        fast = net.prior_update(scores, 1, GRID)
    torch.testing.assert_close(fast, _slow_prior(net, scores, 1, GRID.voxel_size), atol=1e-5, rtol=1e-4)
    # a sharp peak at (rotation i, displacement d) gives exactly that candidate: ω = its Euler offsets,
    # t = −d voxels (the candidate lands the query d voxels too far; see the module doc)
    i, d = 5, 20
    peaked = torch.zeros(1, 27 * 27)
    peaked[0, i * 27 + d] = 100.0
    with torch.no_grad():
        delta = net.prior_update(peaked, 1, GRID)[0]
    torch.testing.assert_close(delta[:3], net.candidate_angles_1[i], atol=1e-6, rtol=0)
    torch.testing.assert_close(delta[3:], -net.displacements[d] * GRID.voxel_size, atol=1e-6, rtol=0)


def test_soft_argmax_translation_sign_recovers_a_known_shift():
    # The query is the reference seen from a frame shifted by 1 m along x (ref0_T_ref1 = +1 m x). On
    # raw features (no encoder) the correlator's estimate must move toward it, not away.
    vol = _smooth_volume(3).repeat(1, 2, 1, 1, 1)[:, :4]  # 1×4×16×4×16
    gt = _pose(0.0, (1.0, 0.0, 0.0))
    query = warp_rigid(vol, gt, GRID)  # query(p) = ref(ref0_T_ref1 · p): the scene seen from ref1
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, scales=(1.0,), rotation_steps_deg=((1.0, 2.0, 1.0),),
                       radius=(1, 1, 1), hidden=8, temperature=8.0)
    with torch.no_grad():
        scores = net.scores(vol, query, torch.eye(4)[None], net.candidates_0, GRID)
        est = se3_exp_update(net.prior_update(scores, 0, GRID))
    err = relative_pose_errors(est, gt)
    assert float(err["trans_err_m"][0]) < 0.5  # identity is 1 m off
    assert float(est[0, 0, 3]) > 0.5


def test_pose_loss_hand_case():
    gt = _pose(0.0, (1.0, 0.0, 0.0))
    est = _pose(math.degrees(0.1), (1.0, 0.5, 0.0))
    loss = pose_loss(est, gt, rotation_weight=1.0)
    # chordal ‖R_e − R_g‖_F/√2 = 2 sin(θ/2) for a rotation by θ
    assert float(loss["rotation"]) == pytest.approx(2 * math.sin(0.05), abs=1e-5)
    assert float(loss["translation"]) == pytest.approx(0.5, abs=1e-6)


def test_encode_then_align_is_the_forward():
    """A stream encodes each frame once (`encode`) and aligns kept encodings (`align`): in eval mode that is
    the forward pass, which encodes both volumes in one batch."""
    torch.manual_seed(0)
    net = EgomotionNet(grid=GRID, width=4, feature_dim=4, radius=(1, 1, 1), hidden=16).eval()
    for head in net.heads:
        torch.nn.init.normal_(head[-1].weight, std=0.05)
    ref_in, query_in = torch.randn(2, 4, 16, 4, 16), torch.randn(2, 4, 16, 4, 16)
    with torch.no_grad():
        whole = net(ref_in, query_in)
        parts = net.align(net.encode(ref_in), net.encode(query_in))
    assert not torch.allclose(whole["ref0_T_ref1"], torch.eye(4).expand(2, 4, 4), atol=1e-3)
    torch.testing.assert_close(parts["ref0_T_ref1"], whole["ref0_T_ref1"], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(parts["per_scale"], whole["per_scale"], atol=1e-5, rtol=1e-5)
    with pytest.raises(Exception, match="query_feat"):
        net.align(net.encode(ref_in), net.encode(query_in)[:1])
