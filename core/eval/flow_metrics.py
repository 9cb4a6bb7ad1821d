"""3D flow errors in voxel units: the paper's L1 EPE split full/static/moving, plus scene-flow scores.

Conventions (docs/conventions.md#3d-flow): flow volumes are B×3×Z×Y×X, channels (x, y, z), in voxels, from t to t+1.

Definitions (all in voxels; documented once here and echoed in reports):
- L1 EPE (the paper's table): per voxel Σ_c |pred_c − gt_c| (L1 norm of the endpoint difference),
  averaged over the voxels of a split. Splits: `full` = all evaluated voxels, `moving` = voxels whose
  ground-truth flow has L2 norm > `moving_threshold` (default 1e-3 voxel: any real motion), `static` =
  the rest. The evaluated voxels are the `valid` mask (default: all voxels).
- Scene-flow scores on OCCUPIED voxels (FlowNet3D's kinds of score, with n3dmap's own absolute thresholds in
  voxels: FlowNet3D's 0.05 m / 0.1 m would be 0.2 / 0.4 voxel at the paper's 0.25 m voxels, so the strict and
  relaxed scores here are looser; only the outlier threshold is FlowNet3D's 0.3 m re-expressed):
  EPE3D = mean L2 norm of the error; relative error = EPE3D / ‖gt‖₂ on moving voxels;
  Acc3DS (strict) = fraction with EPE < 0.5 voxel OR relative error < 5%;
  Acc3DR (relaxed) = fraction with EPE < 1 voxel OR relative error < 10%;
  Outliers = fraction with EPE > 1.2 voxel (0.3 m at the paper's 0.25 m voxels) OR relative error > 10%.
  On static voxels (ground-truth norm ≤ `moving_threshold`) relative error is undefined and only the
  absolute thresholds apply: otherwise every static voxel with any error would be an outlier — and a
  static voxel's true flow is rarely exactly zero (the float32 pose round trip of `gt_flow` leaves
  ~1e-6 voxel), so the test must use the same threshold as the moving split, not "> 0".

Dataset-level numbers are ratios of sums (every voxel weighs the same), so the functions return sums and
counts (`flow_error_sums`) that `flow_scores` turns into scores; both are pure.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError, check_shape

STRICT_ABS, STRICT_REL = 0.5, 0.05
RELAXED_ABS, RELAXED_REL = 1.0, 0.10
OUTLIER_ABS, OUTLIER_REL = 1.2, 0.10
SPLITS = ("full", "static", "moving")


def _mask(name: str, m: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    B, _, Z, Y, X = like.shape
    if m is None:
        return torch.ones(B, 1, Z, Y, X, dtype=torch.bool, device=like.device)
    check_shape(name, m, (B, 1, Z, Y, X))
    return m.bool()


def flow_error_sums(pred: torch.Tensor, gt: torch.Tensor, *, valid: torch.Tensor | None = None,
                    occupied: torch.Tensor | None = None, moving_threshold: float = 1e-3) -> dict[str, float]:
    """Sums and counts for one batch.

    pred, gt: B×3×Z×Y×X flow (voxels). valid: B×1×Z×Y×X bool voxels evaluated for the L1 splits (None:
    all). occupied: B×1×Z×Y×X bool voxels for the scene-flow scores (None: all valid voxels).
    Returns floats: `l1_sum_<split>`, `count_<split>`, `epe3d_sum`, `acc3ds_count`, `acc3dr_count`,
    `outlier_count`, `occ_count`.
    """
    check_shape("pred", pred, (None, 3, None, None, None))
    check_shape("gt", gt, tuple(pred.shape))
    if not (torch.isfinite(pred).all() and torch.isfinite(gt).all()):
        raise ShapeError("flow_error_sums: pred and gt must be finite")
    valid = _mask("valid", valid, pred)
    occupied = valid if occupied is None else (_mask("occupied", occupied, pred) & valid)
    diff = (pred.double() - gt.double())  # B×3×Z×Y×X
    l1 = diff.abs().sum(1, keepdim=True)  # B×1×Z×Y×X
    epe = diff.norm(dim=1, keepdim=True)  # B×1×Z×Y×X
    gt_norm = gt.double().norm(dim=1, keepdim=True)  # B×1×Z×Y×X
    moving = (gt_norm > moving_threshold) & valid
    static = (~moving) & valid
    out: dict[str, float] = {}
    for split, m in (("full", valid), ("static", static), ("moving", moving)):
        out[f"l1_sum_{split}"] = float(l1[m].sum())
        out[f"count_{split}"] = float(m.sum())
    has_rel = gt_norm > moving_threshold  # relative error only where the voxel moves (module docstring)
    rel = torch.where(has_rel, epe / gt_norm.clamp_min(moving_threshold), torch.zeros_like(epe))
    strict = (epe < STRICT_ABS) | (has_rel & (rel < STRICT_REL))
    relaxed = (epe < RELAXED_ABS) | (has_rel & (rel < RELAXED_REL))
    outlier = (epe > OUTLIER_ABS) | (has_rel & (rel > OUTLIER_REL))
    out["epe3d_sum"] = float(epe[occupied].sum())
    out["acc3ds_count"] = float((strict & occupied).sum())
    out["acc3dr_count"] = float((relaxed & occupied).sum())
    out["outlier_count"] = float((outlier & occupied).sum())
    out["occ_count"] = float(occupied.sum())
    return out


def add_sums(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    """Element-wise sum of two `flow_error_sums` dicts (an empty dict is the identity)."""
    return {k: a.get(k, 0.0) + b.get(k, 0.0) for k in set(a) | set(b)}


def flow_scores(sums: dict[str, float]) -> dict[str, float]:
    """Turn accumulated sums into scores: `epe_l1_<split>`, `epe3d`, `acc3ds`, `acc3dr`, `outliers`
    (NaN where the split is empty) plus the voxel counts."""
    def ratio(n: float, d: float) -> float:
        return n / d if d > 0 else float("nan")

    out = {f"epe_l1_{s}": ratio(sums.get(f"l1_sum_{s}", 0.0), sums.get(f"count_{s}", 0.0)) for s in SPLITS}
    occ = sums.get("occ_count", 0.0)
    out["epe3d"] = ratio(sums.get("epe3d_sum", 0.0), occ)
    out["acc3ds"] = ratio(sums.get("acc3ds_count", 0.0), occ)
    out["acc3dr"] = ratio(sums.get("acc3dr_count", 0.0), occ)
    out["outliers"] = ratio(sums.get("outlier_count", 0.0), occ)
    for s in SPLITS:
        out[f"voxels_{s}"] = int(sums.get(f"count_{s}", 0.0))
    out["voxels_occupied"] = int(occ)
    return out
