"""Anchor matching and balanced sampling on hand-built cases."""

from __future__ import annotations

import torch

from core.models.detector_targets import assign_anchors, sample_anchors


def _box(x, z, lx=2.0, lz=2.0, y=0.0, ly=1.0):
    return [x, y, z, lx, ly, lz]


def test_assignment_hand_built_case():
    anchors = torch.tensor([
        _box(0.0, 0.0),            # 0: identical to gt 0 -> positive (IoU 1)
        _box(0.5, 0.0),            # 1: BEV IoU 1.5·2 / (8 − 3) = 0.6 with gt 0 -> positive
        _box(1.0, 0.0),            # 2: IoU 2 / 6 = 0.333 -> ignored (between 0.3 and 0.5)
        _box(1.5, 0.0),            # 3: IoU 1 / 7 = 0.143 -> negative
        _box(10.0, 10.0),          # 4: far from everything -> negative
        _box(20.6, 0.0, y=5.0),    # 5: gt 1's best anchor, though its IoU is low (see below)
    ])
    gt = torch.tensor([_box(0.0, 0.0), _box(20.0, 0.0, lx=4.0, lz=4.0)])
    # anchor 5 vs gt 1: overlap x [19.6, 21.6]∩[18, 22] = 2, z [−1, 1]∩[−2, 2] = 2 -> 4 / (4 + 16 − 4) = 0.25:
    # below the negative threshold, but it is gt 1's best anchor, so it is positive and matched to gt 1.
    # The height (y) does not enter the matching (bird's-eye view).
    labels, matched = assign_anchors(anchors, gt, positive_iou=0.5, negative_iou=0.3)
    assert labels.tolist() == [1, 1, -1, 0, 0, 1]
    assert matched[0] == 0 and matched[1] == 0 and matched[5] == 1


def test_assignment_without_ground_truth_is_all_negative():
    anchors = torch.tensor([_box(0.0, 0.0), _box(3.0, 0.0)])
    labels, _ = assign_anchors(anchors, torch.zeros(0, 6), positive_iou=0.5, negative_iou=0.3)
    assert labels.tolist() == [0, 0]


def test_balanced_sampling_caps_positives_and_fills_with_negatives():
    labels = torch.tensor([1] * 30 + [0] * 100 + [-1] * 20)
    gen = torch.Generator().manual_seed(0)
    pos, neg = sample_anchors(labels, num_samples=40, positive_fraction=0.5, generator=gen)
    assert int(pos.sum()) == 20 and int(neg.sum()) == 20
    assert bool((labels[pos] == 1).all()) and bool((labels[neg] == 0).all())
    # few positives: negatives fill the rest
    labels = torch.tensor([1] * 3 + [0] * 100)
    pos, neg = sample_anchors(labels, num_samples=40, positive_fraction=0.5, generator=gen)
    assert int(pos.sum()) == 3 and int(neg.sum()) == 37
