"""Egomotion error per frame pair, as TUM's relative pose error (RPE) and the paper's Table (R rad, t m).

Conventions (docs/conventions.md#poses): poses are 4×4 `a_T_b` with p_a = a_T_b @ p_b. Both the estimate and the
ground truth must be the SAME relative pose (e.g. both `ref0_T_ref1`, or both `cam0_T_cam1`). The error
transform is `err = inv(gt) · est` (TUM RPE with a step of one pair); its rotation angle (radians, in
[0, π]) is the rotation error and the norm of its translation (metres) the translation error.
"""

from __future__ import annotations

import math

import torch

from core.errors import check_shape
from core.geometry import se3


def relative_pose_errors(est_T: torch.Tensor, gt_T: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-pair errors of estimated vs ground-truth relative poses.

    est_T, gt_T: B×4×4 (same frames). Returns dict of B tensors (float64):
      `rot_err_rad`, `rot_err_deg` (angle of inv(gt)·est), `trans_err_m` (‖t of inv(gt)·est‖₂).
    """
    check_shape("est_T", est_T, (None, 4, 4))
    check_shape("gt_T", gt_T, (est_T.shape[0], 4, 4))
    err = se3.invert(gt_T.double()) @ est_T.double()  # B×4×4
    rot = se3.rotation_angle(err[:, :3, :3])
    trans = err[:, :3, 3].norm(dim=-1)
    return {"rot_err_rad": rot, "rot_err_deg": rot * (180.0 / math.pi), "trans_err_m": trans}


def summarize_errors(errors: dict[str, torch.Tensor]) -> dict[str, float]:
    """Mean, median and RMSE of each per-pair error list. errors: name -> N. Returns `name_mean` etc."""
    out: dict[str, float] = {}
    for name, values in errors.items():
        v = values.double().flatten()
        if v.numel() == 0:
            out.update({f"{name}_mean": float("nan"), f"{name}_median": float("nan"), f"{name}_rmse": float("nan")})
            continue
        out[f"{name}_mean"] = float(v.mean())
        out[f"{name}_median"] = float(v.median())
        out[f"{name}_rmse"] = float(v.square().mean().sqrt())
    out["pairs"] = int(next(iter(errors.values())).numel()) if errors else 0
    return out
