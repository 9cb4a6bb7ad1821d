"""Occupancy accuracy on labelled voxels (occupied / free / all) and occupied IoU.

Labels are partial (the paper's protocol): `occupied` voxels hold a point, `free` voxels are crossed by
a camera ray; everything else is unlabelled and ignored. A voxel labelled both (e.g. seen free from one
view and occupied from another) counts as occupied. A prediction is "occupied" when its probability is
>= `threshold`.
- acc_occupied = correct among occupied-labelled, acc_free = correct among free-labelled,
  acc_all = correct among all labelled voxels;
- iou_occupied = |pred_occ ∧ label_occ| / |(pred_occ ∨ label_occ) ∧ labelled| (IoU restricted to the
  labelled voxels, since unlabelled ones have no truth).
Dataset-level scores are ratios of summed counts (`occupancy_counts` then `occupancy_scores`).
"""

from __future__ import annotations

import torch

from core.errors import check_shape


def occupancy_counts(prob: torch.Tensor, occupied: torch.Tensor, free: torch.Tensor, *,
                     threshold: float = 0.5) -> dict[str, float]:
    """prob: B×1×Z×Y×X in [0, 1]; occupied, free: B×1×Z×Y×X bool labels. Returns counts:
    `n_occupied`, `n_free`, `correct_occupied`, `correct_free`, `intersection`, `union`."""
    check_shape("prob", prob, (None, 1, None, None, None))
    check_shape("occupied", occupied, tuple(prob.shape))
    check_shape("free", free, tuple(prob.shape))
    occ = occupied.bool()
    fre = free.bool() & ~occ
    pred = prob >= threshold
    labelled = occ | fre
    return {
        "n_occupied": float(occ.sum()), "n_free": float(fre.sum()),
        "correct_occupied": float((pred & occ).sum()), "correct_free": float((~pred & fre).sum()),
        "intersection": float((pred & occ).sum()), "union": float(((pred | occ) & labelled).sum()),
    }


def add_counts(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    """Element-wise sum of two count dicts (an empty dict is the identity)."""
    return {k: a.get(k, 0.0) + b.get(k, 0.0) for k in set(a) | set(b)}


def occupancy_scores(counts: dict[str, float]) -> dict[str, float]:
    """Counts -> `acc_occupied`, `acc_free`, `acc_all`, `iou_occupied` (NaN where undefined) + sizes."""
    def ratio(n: float, d: float) -> float:
        return n / d if d > 0 else float("nan")

    n_occ, n_free = counts.get("n_occupied", 0.0), counts.get("n_free", 0.0)
    c_occ, c_free = counts.get("correct_occupied", 0.0), counts.get("correct_free", 0.0)
    return {
        "acc_occupied": ratio(c_occ, n_occ), "acc_free": ratio(c_free, n_free),
        "acc_all": ratio(c_occ + c_free, n_occ + n_free),
        "iou_occupied": ratio(counts.get("intersection", 0.0), counts.get("union", 0.0)),
        "voxels_occupied": int(n_occ), "voxels_free": int(n_free),
    }
