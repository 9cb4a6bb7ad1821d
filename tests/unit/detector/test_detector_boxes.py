"""Axis-aligned box helpers of the detector against slow, obvious per-element references."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from core.eval.iou3d import iou_3d, iou_bev
from core.geometry.grid import GridConfig
from core.models.detector_anchors import anchor_grid, coarse_shape
from core.models.detector_boxes import (
    aabb_iou, aabb_to_boxes, boxes_to_aabb, decode_deltas, encode_deltas, nms_aabb,
)
from core.errors import ShapeError


def _random_aabb(n: int, gen: torch.Generator) -> torch.Tensor:
    centre = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 10 - 5
    size = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 4 + 0.5
    return torch.cat([centre, size], dim=1)


def _slow_encode(anchor, target):
    return ([(target[i] - anchor[i]) / anchor[3 + i] for i in range(3)]
            + [math.log(target[3 + i] / anchor[3 + i]) for i in range(3)])


def _slow_decode(anchor, delta):
    return ([anchor[i] + delta[i] * anchor[3 + i] for i in range(3)]
            + [anchor[3 + i] * math.exp(delta[3 + i]) for i in range(3)])


def test_delta_coding_matches_slow_reference_and_round_trips():
    gen = torch.Generator().manual_seed(0)
    anchors, targets = _random_aabb(50, gen), _random_aabb(50, gen)
    deltas = encode_deltas(anchors, targets)
    slow = torch.tensor([_slow_encode(a.tolist(), t.tolist()) for a, t in zip(anchors, targets)], dtype=torch.float64)
    torch.testing.assert_close(deltas, slow, rtol=1e-12, atol=1e-12)
    decoded = decode_deltas(anchors, deltas)
    slow_decoded = torch.tensor([_slow_decode(a.tolist(), d.tolist()) for a, d in zip(anchors, deltas)],
                                dtype=torch.float64)
    torch.testing.assert_close(decoded, slow_decoded, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(decoded, targets, rtol=1e-12, atol=1e-12)


def test_decode_caps_huge_size_deltas():
    anchor = torch.tensor([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0]])
    box = decode_deltas(anchor, torch.tensor([[0.0, 0.0, 0.0, 100.0, 0.0, 0.0]]))
    assert torch.isfinite(box).all() and box[0, 3] == pytest.approx(1000.0 / 16.0, rel=1e-5)


def test_boxes_to_aabb_against_corner_loop_and_back():
    gen = torch.Generator().manual_seed(1)
    boxes = torch.cat([_random_aabb(20, gen), torch.rand(20, 1, generator=gen, dtype=torch.float64) * 6 - 3], 1)
    aabb = boxes_to_aabb(boxes)
    for box, got in zip(boxes.tolist(), aabb.tolist()):
        x, y, z, lx, ly, lz, yaw = box
        c, s = math.cos(yaw), math.sin(yaw)
        xs, zs = [], []
        for sx, sz in itertools.product((-0.5, 0.5), repeat=2):
            ox, oz = sx * lx, sz * lz
            xs.append(x + c * ox + s * oz)   # R = [[c,0,s],[0,1,0],[-s,0,c]]
            zs.append(z - s * ox + c * oz)
        want = [(max(xs) + min(xs)) / 2, y, (max(zs) + min(zs)) / 2, max(xs) - min(xs), ly, max(zs) - min(zs)]
        assert got == pytest.approx(want, abs=1e-9)
    # yaw 0 boxes are their own bounding boxes
    torch.testing.assert_close(boxes_to_aabb(aabb_to_boxes(aabb)), aabb)


def test_aabb_iou_matches_exact_oriented_iou_at_yaw_zero():
    gen = torch.Generator().manual_seed(2)
    a, b = _random_aabb(15, gen), _random_aabb(12, gen)
    b[:5] = a[:5] + 0.3  # some heavy overlaps
    torch.testing.assert_close(aabb_iou(a, b).numpy(), iou_3d(aabb_to_boxes(a).numpy(), aabb_to_boxes(b).numpy()),
                               rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(aabb_iou(a, b, dims=(0, 2)).numpy(),
                               iou_bev(aabb_to_boxes(a).numpy(), aabb_to_boxes(b).numpy()), rtol=1e-9, atol=1e-9)


def test_aabb_iou_hand_case():
    a = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0]])
    b = torch.tensor([[1.0, 0.0, 0.0, 2.0, 2.0, 2.0], [5.0, 0.0, 0.0, 2.0, 2.0, 2.0]])
    # overlap 1×2×2 = 4, union 8 + 8 − 4 = 12
    torch.testing.assert_close(aabb_iou(a, b), torch.tensor([[4 / 12, 0.0]]))


def _slow_iou3d(a, b):
    inter = 1.0
    for i in range(3):
        lo = max(a[i] - a[3 + i] / 2, b[i] - b[3 + i] / 2)
        hi = min(a[i] + a[3 + i] / 2, b[i] + b[3 + i] / 2)
        inter *= max(0.0, hi - lo)
    return inter / (a[3] * a[4] * a[5] + b[3] * b[4] * b[5] - inter)


def _slow_nms(aabb, scores, thr):
    order = sorted(range(len(scores)), key=lambda i: -scores[i])
    keep = []
    for i in order:
        if all(_slow_iou3d(aabb[i], aabb[j]) <= thr for j in keep):
            keep.append(i)
    return keep


def test_nms_matches_slow_greedy_reference():
    gen = torch.Generator().manual_seed(3)
    centres = torch.rand(40, 3, generator=gen) * 6
    aabb = torch.cat([centres, torch.full((40, 3), 2.0)], dim=1)
    scores = torch.rand(40, generator=gen)
    for thr in (0.1, 0.3, 0.6):
        assert nms_aabb(aabb, scores, thr).tolist() == _slow_nms(aabb.tolist(), scores.tolist(), thr)
    assert nms_aabb(aabb[:0], scores[:0], 0.3).numel() == 0


def test_anchor_grid_centres_and_order():
    grid = GridConfig(xmin=-4.0, xmax=4.0, ymin=-2.0, ymax=2.0, zmin=0.0, zmax=8.0, Z=8, Y=4, X=8)
    sizes = ((4.0, 1.5, 2.0), (2.0, 1.5, 4.0))
    anchors = anchor_grid(grid, stride=2, sizes=sizes, y_centre=1.0)
    Zc, Yc, Xc = coarse_shape(grid, 2)
    assert (Zc, Yc, Xc) == (4, 2, 4) and anchors.shape == (Zc * Xc * 2, 6)
    for iz, ix, a in itertools.product(range(Zc), range(Xc), range(2)):
        row = anchors[(iz * Xc + ix) * 2 + a].tolist()
        assert row == pytest.approx([-4.0 + (ix + 0.5) * 2.0, 1.0, (iz + 0.5) * 2.0, *sizes[a]])
    with pytest.raises(ShapeError, match="stride 3"):
        coarse_shape(grid, 3)
