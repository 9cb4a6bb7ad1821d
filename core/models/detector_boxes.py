"""Axis-aligned 3D boxes for the detector: conversion, IoU, Faster-RCNN delta coding and NMS.

Conventions (docs/conventions.md#boxes): boxes live in `ref` (X right, Y down, Z forward, metres). The detector
works with axis-aligned boxes ("aabb"), rows (x, y, z, lx, ly, lz): centre and extents along the
frame's own axes. The paper's detector is axis-aligned, so a yaw-rotated ground-truth box is
replaced by its axis-aligned bounding box (`boxes_to_aabb`), and detections go back to canonical
boxes with yaw 0 (`aabb_to_boxes`). Shapes: N×6 / N×7 (any leading dims where noted).

Delta coding (Ren et al., Faster R-CNN, in 3D): for an anchor a and a target g,
    d_c = (g_c − a_c) / a_l   for each axis (centre offset in units of the anchor's length on that axis)
    d_l = log(g_l / a_l)      for each axis (log size ratio)
so deltas are rows (dx, dy, dz, dlx, dly, dlz).
"""

from __future__ import annotations

import math

import torch

from core.geometry.boxes import box_corners

# exp() of a size delta is capped here (as torchvision's BoxCoder: log(1000/16)) so a wild
# prediction early in training cannot overflow.
_MAX_LOG_SIZE_DELTA = math.log(1000.0 / 16.0)


def boxes_to_aabb(boxes: torch.Tensor) -> torch.Tensor:
    """Canonical yaw-rotated boxes …×7 -> their axis-aligned bounding boxes …×6 (same frame)."""
    corners = box_corners(boxes)                       # …×8×3
    lo, hi = corners.amin(dim=-2), corners.amax(dim=-2)  # …×3
    return torch.cat([0.5 * (lo + hi), hi - lo], dim=-1)


def aabb_to_boxes(aabb: torch.Tensor) -> torch.Tensor:
    """Axis-aligned boxes …×6 -> canonical boxes …×7 with yaw 0."""
    return torch.cat([aabb, aabb.new_zeros(*aabb.shape[:-1], 1)], dim=-1)


def aabb_iou(a: torch.Tensor, b: torch.Tensor, *, dims: tuple[int, ...] = (0, 1, 2)) -> torch.Tensor:
    """Pairwise IoU of axis-aligned boxes over the axes `dims` (0 = x, 1 = y, 2 = z).

    a: N×6, b: M×6 -> N×M. dims=(0, 1, 2) is the 3D IoU (volumes); dims=(0, 2) the bird's-eye-view IoU
    (areas in the x–z plane). Empty boxes give IoU 0.
    """
    idx = list(dims)
    ca, la = a[:, None, idx], a[:, None, [3 + d for d in idx]]  # N×1×D
    cb, lb = b[None, :, idx], b[None, :, [3 + d for d in idx]]  # 1×M×D
    lo = torch.maximum(ca - 0.5 * la, cb - 0.5 * lb)            # N×M×D
    hi = torch.minimum(ca + 0.5 * la, cb + 0.5 * lb)
    inter = (hi - lo).clamp(min=0).prod(dim=-1)                 # N×M
    union = la.prod(dim=-1) + lb.prod(dim=-1) - inter           # N×M
    return torch.where(union > 0, inter / union.clamp(min=1e-12), torch.zeros_like(inter))


def encode_deltas(anchors: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Regression targets of `targets` relative to `anchors`: both …×6 -> deltas …×6 (see module doc)."""
    d_centre = (targets[..., :3] - anchors[..., :3]) / anchors[..., 3:]
    d_size = torch.log(targets[..., 3:] / anchors[..., 3:])
    return torch.cat([d_centre, d_size], dim=-1)


def decode_deltas(anchors: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Inverse of `encode_deltas`: anchors …×6, deltas …×6 -> boxes …×6 (size deltas capped)."""
    centre = anchors[..., :3] + deltas[..., :3] * anchors[..., 3:]
    size = anchors[..., 3:] * torch.exp(deltas[..., 3:].clamp(max=_MAX_LOG_SIZE_DELTA))
    return torch.cat([centre, size], dim=-1)


def nms_aabb(aabb: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy non-maximum suppression of axis-aligned 3D boxes by 3D IoU (torch, any device).

    aabb: N×6, scores: N -> kept indices (int64), highest score first. A box is dropped when its
    IoU with an already kept box exceeds `iou_threshold`.
    """
    order = torch.argsort(scores, descending=True, stable=True)
    if order.numel() == 0:
        return order
    iou = aabb_iou(aabb[order], aabb[order])                    # N×N, rows/cols in score order
    # Greedy pass on the (small, pre-filtered) candidate set; the loop is over kept boxes only.
    overlaps = (iou > iou_threshold).cpu()                      # N×N bool
    suppressed = torch.zeros(order.numel(), dtype=torch.bool)
    keep = []
    for i in range(order.numel()):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= overlaps[i]
    return order[torch.tensor(keep, dtype=torch.long, device=aabb.device)]
