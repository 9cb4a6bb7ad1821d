"""Class-balanced logistic loss for occupancy (paper appendix).

Labels come from depth: voxels where points land are occupied, voxels the camera rays cross before
their point are free; everything else is unlabelled. Free voxels far outnumber occupied ones, so the
loss averages each class separately within the minibatch and takes the mean of the two.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def balanced_occupancy_loss(logits: torch.Tensor, occupied: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """logits, occupied, free: B×1×Z×Y×X (labels in {0, 1}; a voxel both occupied and free counts as
    occupied). Returns a scalar; a class with no labels contributes nothing."""
    logits = logits.float()
    occ = occupied.float()
    free = free.float() * (1.0 - occ)
    pos = F.softplus(-logits)  # -log sigmoid(logit)
    neg = F.softplus(logits)   # -log (1 - sigmoid(logit))
    terms = []
    if occ.sum() > 0:
        terms.append((pos * occ).sum() / occ.sum())
    if free.sum() > 0:
        terms.append((neg * free).sum() / free.sum())
    if not terms:
        return logits.sum() * 0.0
    return torch.stack(terms).mean()


def occupancy_accuracy(logits: torch.Tensor, occupied: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """Class-balanced accuracy at threshold 0.5 (mean of occupied recall and free recall)."""
    pred = logits > 0
    occ = occupied > 0.5
    free = (free > 0.5) & ~occ
    accs = [((pred & occ).sum() / occ.sum()).float()] if occ.any() else []
    if free.any():
        accs.append(((~pred & free).sum() / free.sum()).float())
    return torch.stack(accs).mean() if accs else logits.new_zeros(())
