"""Egomotion, flow and occupancy metrics against hand-computed cases."""

import math

import pytest
import torch

from core.errors import ShapeError
from core.eval.egomotion_metrics import relative_pose_errors, summarize_errors
from core.eval.flow_metrics import add_sums, flow_error_sums, flow_scores
from core.eval.occupancy_metrics import add_counts, occupancy_counts, occupancy_scores
from core.geometry import se3


def _yaw_pose(yaw: float, t: tuple[float, float, float]) -> torch.Tensor:
    return se3.from_rt(se3.yaw_to_matrix(torch.tensor([yaw], dtype=torch.float64)),
                       torch.tensor([t], dtype=torch.float64))


# ----------------------------------------------------------------------------- egomotion

def test_rpe_identity_is_zero():
    T = _yaw_pose(0.3, (1.0, 0.0, 2.0))
    e = relative_pose_errors(T, T)
    assert e["rot_err_rad"].abs().max() < 1e-9 and e["trans_err_m"].abs().max() < 1e-9


def test_rpe_hand_case():
    # gt: pure translation (1, 0, 0); est: yaw 0.1 rad and translation (1, 0, 0.5).
    # err = inv(gt)·est = [R_est | t_est - t_gt] -> angle 0.1 rad, translation 0.5 m.
    gt = _yaw_pose(0.0, (1.0, 0.0, 0.0))
    est = _yaw_pose(0.1, (1.0, 0.0, 0.5))
    e = relative_pose_errors(est, gt)
    assert e["rot_err_rad"].item() == pytest.approx(0.1, abs=1e-9)
    assert e["rot_err_deg"].item() == pytest.approx(0.1 * 180 / math.pi, abs=1e-7)
    assert e["trans_err_m"].item() == pytest.approx(0.5, abs=1e-9)


def test_rpe_frame_of_translation_error():
    # gt rotates by 90° about Y; est = gt + 1 m along ref0 x. inv(gt)·est expresses that 1 m in gt's frame,
    # whose norm is still 1 m.
    gt = _yaw_pose(math.pi / 2, (0.0, 0.0, 0.0))
    est = gt.clone()
    est[0, 0, 3] += 1.0
    e = relative_pose_errors(est, gt)
    assert e["trans_err_m"].item() == pytest.approx(1.0, abs=1e-9)
    assert e["rot_err_rad"].item() == pytest.approx(0.0, abs=1e-7)


def test_summaries():
    s = summarize_errors({"x": torch.tensor([1.0, 2.0, 4.0])})
    assert s["x_mean"] == pytest.approx(7 / 3)
    assert s["x_median"] == pytest.approx(2.0)
    assert s["x_rmse"] == pytest.approx(math.sqrt(21 / 3))
    assert s["pairs"] == 3


def test_rpe_bad_shape():
    with pytest.raises(ShapeError):
        relative_pose_errors(torch.eye(4)[None], torch.eye(3)[None])


# ----------------------------------------------------------------------------- flow

def _flow_case():
    # 1×3×1×1×4 volume: voxel 0 static, perfect; voxel 1 static, pred (1,0,0);
    # voxel 2 moving gt (2,0,0), pred (2,1,0); voxel 3 moving gt (10,0,0), pred (10.5,0,0).
    gt = torch.zeros(1, 3, 1, 1, 4)
    pred = torch.zeros(1, 3, 1, 1, 4)
    pred[0, 0, 0, 0, 1] = 1.0
    gt[0, 0, 0, 0, 2] = 2.0
    pred[0, :2, 0, 0, 2] = torch.tensor([2.0, 1.0])
    gt[0, 0, 0, 0, 3] = 10.0
    pred[0, 0, 0, 0, 3] = 10.5
    return pred, gt


def test_flow_l1_splits_hand_case():
    pred, gt = _flow_case()
    s = flow_scores(flow_error_sums(pred, gt))
    # L1 errors per voxel: 0, 1, 1, 0.5
    assert s["epe_l1_full"] == pytest.approx(2.5 / 4)
    assert s["epe_l1_static"] == pytest.approx(1 / 2)
    assert s["epe_l1_moving"] == pytest.approx(1.5 / 2)
    # zero-motion row: static 0, moving (2 + 10) / 2
    z = flow_scores(flow_error_sums(torch.zeros_like(gt), gt))
    assert z["epe_l1_static"] == 0.0 and z["epe_l1_moving"] == pytest.approx(6.0)


def test_flow_l1_differs_from_l2():
    gt = torch.zeros(1, 3, 1, 1, 1)
    pred = torch.ones(1, 3, 1, 1, 1)
    s = flow_scores(flow_error_sums(pred, gt))
    assert s["epe_l1_full"] == pytest.approx(3.0)
    assert s["epe3d"] == pytest.approx(math.sqrt(3.0))


def test_flow_scene_flow_scores_hand_case():
    pred, gt = _flow_case()
    s = flow_scores(flow_error_sums(pred, gt))
    # EPE3D: 0, 1, 1, 0.5 -> 0.625. relative: voxel 2: 1/2 = 50 %, voxel 3: 0.5/10 = 5 %.
    assert s["epe3d"] == pytest.approx(2.5 / 4)
    # strict (<0.5 or rel<5%): voxel 0 yes, 1 no, 2 no, 3 no (0.5 !< 0.5, 5% !< 5%) -> 1/4
    assert s["acc3ds"] == pytest.approx(0.25)
    # relaxed (<1 or rel<10%): voxel 0 yes, 1 no (1 !< 1, no gt), 2 no, 3 yes -> 2/4
    assert s["acc3dr"] == pytest.approx(0.5)
    # outliers (>1.2 or rel>10%): voxel 2 only (rel 50 %) -> 1/4
    assert s["outliers"] == pytest.approx(0.25)


def test_flow_static_voxels_with_pose_round_off_are_judged_by_the_absolute_thresholds_only():
    # static voxels whose true flow is 1e-6 voxel (the float32 pose round trip of gt_flow), predicted
    # 1e-4 voxel off: nearly exact, so no outliers and both accuracies 1 — a relative test against
    # 1e-6 would call every one an outlier (error 100 × the "motion"); the moving voxel keeps its test
    gt = torch.full((1, 3, 1, 1, 3), 1e-6)
    gt[0, 0, 0, 0, 2] = 2.0                  # moving: pred 0.3 voxel off, 15 % relative error
    pred = gt + 1e-4
    pred[0, 0, 0, 0, 2] = 2.3
    s = flow_scores(flow_error_sums(pred, gt))
    assert s["outliers"] == pytest.approx(1 / 3)   # the moving voxel only (rel 15 % > 10 %)
    assert s["acc3ds"] == pytest.approx(1.0) and s["acc3dr"] == pytest.approx(1.0)   # 0.3 < 0.5 voxel
    assert s["voxels_moving"] == 1


def test_flow_masks_and_accumulation():
    pred, gt = _flow_case()
    occupied = torch.tensor([True, False, True, False]).view(1, 1, 1, 1, 4)
    s = flow_scores(flow_error_sums(pred, gt, occupied=occupied))
    assert s["epe3d"] == pytest.approx(0.5)  # voxels 0 and 2: (0 + 1) / 2
    valid = torch.tensor([False, True, True, True]).view(1, 1, 1, 1, 4)
    a = flow_error_sums(pred, gt, valid=valid)
    total = flow_scores(add_sums(a, a))
    assert total["epe_l1_full"] == pytest.approx(2.5 / 3)
    assert total["voxels_full"] == 6


def test_flow_empty_split_is_nan():
    s = flow_scores(flow_error_sums(torch.zeros(1, 3, 1, 1, 2), torch.zeros(1, 3, 1, 1, 2)))
    assert math.isnan(s["epe_l1_moving"]) and s["epe_l1_static"] == 0.0


def test_flow_rejects_bad_input():
    with pytest.raises(ShapeError):
        flow_error_sums(torch.zeros(1, 2, 1, 1, 1), torch.zeros(1, 2, 1, 1, 1))
    with pytest.raises(ShapeError):
        flow_error_sums(torch.full((1, 3, 1, 1, 1), float("nan")), torch.zeros(1, 3, 1, 1, 1))


# ----------------------------------------------------------------------------- occupancy

def test_occupancy_hand_case():
    # 6 voxels: labels occ, occ, free, free, free, none; probs .9, .2, .1, .6, .3, .99
    prob = torch.tensor([0.9, 0.2, 0.1, 0.6, 0.3, 0.99]).view(1, 1, 1, 1, 6)
    occ = torch.tensor([1, 1, 0, 0, 0, 0], dtype=torch.bool).view(1, 1, 1, 1, 6)
    free = torch.tensor([0, 0, 1, 1, 1, 0], dtype=torch.bool).view(1, 1, 1, 1, 6)
    s = occupancy_scores(occupancy_counts(prob, occ, free))
    assert s["acc_occupied"] == pytest.approx(0.5)
    assert s["acc_free"] == pytest.approx(2 / 3)
    assert s["acc_all"] == pytest.approx(3 / 5)
    # pred occ among labelled: voxels 0, 3; label occ: 0, 1 -> inter 1, union 3 (unlabelled 5 ignored)
    assert s["iou_occupied"] == pytest.approx(1 / 3)


def test_occupancy_conflicting_label_counts_as_occupied():
    prob = torch.tensor([0.9]).view(1, 1, 1, 1, 1)
    both = torch.ones(1, 1, 1, 1, 1, dtype=torch.bool)
    c = occupancy_counts(prob, both, both)
    assert c["n_free"] == 0 and c["n_occupied"] == 1
    s = occupancy_scores(add_counts(c, c))
    assert s["acc_all"] == 1.0 and s["voxels_occupied"] == 2
