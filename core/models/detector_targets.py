"""Training targets of the detector: anchor ↔ ground-truth matching and balanced sampling.

As Faster R-CNN's region proposal network, on axis-aligned boxes (detector_boxes) in `ref`:
an anchor is positive when its IoU with some ground-truth box is ≥ `positive_iou`, negative when its
best IoU is < `negative_iou`, ignored in between; in addition, each ground-truth box's best anchor(s)
are positive, so every object gets at least one. Matching uses the bird's-eye-view IoU (x–z plane):
the anchors sit at one fixed height, and the y offset is regressed, not matched.
Each example then contributes a fixed-size sample of anchors with at most `positive_fraction` positives.
"""

from __future__ import annotations

import torch

from core.models.detector_boxes import aabb_iou

BEV_DIMS = (0, 2)


def assign_anchors(anchors: torch.Tensor, gt: torch.Tensor, *, positive_iou: float,
                   negative_iou: float) -> tuple[torch.Tensor, torch.Tensor]:
    """anchors: N×6, gt: K×6 (real boxes only) -> (labels N int64 in {1 pos, 0 neg, −1 ignore},
    matched N int64: index of each anchor's ground-truth box, meaningful where labels == 1)."""
    N = anchors.shape[0]
    if gt.shape[0] == 0:
        return (torch.zeros(N, dtype=torch.long, device=anchors.device),
                torch.zeros(N, dtype=torch.long, device=anchors.device))
    iou = aabb_iou(anchors, gt, dims=BEV_DIMS)                    # N×K
    best_iou, matched = iou.max(dim=1)                            # N, N
    labels = torch.full((N,), -1, dtype=torch.long, device=anchors.device)
    labels[best_iou < negative_iou] = 0
    labels[best_iou >= positive_iou] = 1
    # Each ground-truth box's best anchors (ties included) are positive and matched to that box.
    gt_best = iou.max(dim=0).values                               # K
    is_best = (iou == gt_best[None, :]) & (gt_best[None, :] > 0)  # N×K
    forced = is_best.any(dim=1)                                   # N
    forced_gt = torch.argmax(is_best.to(torch.uint8), dim=1)      # N (first such box)
    matched = torch.where(forced, forced_gt, matched)
    labels[forced] = 1
    return labels, matched


def sample_anchors(labels: torch.Tensor, *, num_samples: int, positive_fraction: float,
                   generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Random balanced subset of labelled anchors: labels N -> (positive mask N, negative mask N).

    At most `num_samples·positive_fraction` positives; negatives fill up to `num_samples`.
    """
    pos = torch.nonzero(labels == 1).squeeze(1)
    neg = torch.nonzero(labels == 0).squeeze(1)
    num_pos = min(pos.numel(), int(num_samples * positive_fraction))
    num_neg = min(neg.numel(), num_samples - num_pos)
    pos = pos[torch.randperm(pos.numel(), generator=generator)[:num_pos].to(labels.device)]
    neg = neg[torch.randperm(neg.numel(), generator=generator)[:num_neg].to(labels.device)]
    pos_mask = torch.zeros_like(labels, dtype=torch.bool)
    neg_mask = torch.zeros_like(labels, dtype=torch.bool)
    pos_mask[pos] = True
    neg_mask[neg] = True
    return pos_mask, neg_mask
