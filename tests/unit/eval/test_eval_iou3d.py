"""Exact oriented IoU against hand-computed cases and a slow Monte-Carlo reference."""

import math

import numpy as np
import pytest
import torch

from core.errors import ShapeError
from core.eval.iou3d import bev_corners, iou_3d, iou_bev


def box(x=0.0, y=0.0, z=0.0, lx=2.0, ly=2.0, lz=2.0, yaw=0.0):
    return np.array([[x, y, z, lx, ly, lz, yaw]])


def _inside(points, b):
    """Slow reference: which of P×3 points lie inside canonical box b (7,)."""
    c, s = math.cos(b[6]), math.sin(b[6])
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # object -> frame
    local = (points - b[:3]) @ R                         # rows: R^T (p - centre)
    return np.all(np.abs(local) <= np.array([b[3], b[4], b[5]]) / 2, axis=1)


def monte_carlo_iou(a, b, n, rng, bev=False):
    """Slow reference IoU by uniform sampling of the joint bounding cube."""
    ra, rb = np.linalg.norm(a[3:6]) / 2, np.linalg.norm(b[3:6]) / 2
    lo = np.minimum(a[:3] - ra, b[:3] - rb)
    hi = np.maximum(a[:3] + ra, b[:3] + rb)
    pts = rng.uniform(lo, hi, size=(n, 3))
    if bev:  # ignore height: give both boxes the same huge vertical extent
        a, b = a.copy(), b.copy()
        a[1] = b[1] = 0.0
        a[4] = b[4] = 1e9
    ia, ib = _inside(pts, a), _inside(pts, b)
    union = np.sum(ia | ib)
    return np.sum(ia & ib) / union if union else 0.0


def test_identical_boxes_have_iou_one():
    b = box(1, 2, 3, 4.0, 1.5, 2.0, 0.7)
    assert iou_3d(b, b)[0, 0] == pytest.approx(1.0, abs=1e-12)
    assert iou_bev(b, b)[0, 0] == pytest.approx(1.0, abs=1e-12)


def test_disjoint_boxes_have_iou_zero():
    assert iou_3d(box(), box(x=5))[0, 0] == 0.0
    assert iou_bev(box(), box(z=-2.5, yaw=0.3))[0, 0] == 0.0
    # Same footprint, disjoint heights: BEV IoU 1, 3D IoU 0.
    assert iou_3d(box(), box(y=2.0))[0, 0] == 0.0
    assert iou_bev(box(), box(y=2.0))[0, 0] == pytest.approx(1.0)


def test_half_shifted_axis_aligned_cube_is_one_third():
    # Overlap is half of each cube: 4 / (8 + 8 - 4) = 1/3, in x, in z, and in height.
    for shift in (dict(x=1.0), dict(z=-1.0), dict(y=1.0)):
        assert iou_3d(box(), box(**shift))[0, 0] == pytest.approx(1 / 3, abs=1e-12)


def test_square_rotated_by_90_degrees_is_identical():
    assert iou_3d(box(), box(yaw=math.pi / 2))[0, 0] == pytest.approx(1.0, abs=1e-12)
    # A 4×2 rectangle turned 90°: overlap 2×2 = 4, union 8 + 8 - 4 = 12.
    assert iou_bev(box(lx=4, lz=2), box(lx=4, lz=2, yaw=math.pi / 2))[0, 0] == pytest.approx(1 / 3, abs=1e-12)


def test_45_degree_square_overlap_is_the_regular_octagon():
    # Two side-2 squares, one turned 45°, share a regular octagon of area 8(√2 − 1).
    octagon = 8 * (math.sqrt(2) - 1)
    expected = octagon / (4 + 4 - octagon)
    assert iou_bev(box(), box(yaw=math.pi / 4))[0, 0] == pytest.approx(expected, abs=1e-12)
    # With a height offset of 0.5 (overlap 1.5 of 2): 3D IoU = 1.5·oct / (8 + 8 − 1.5·oct).
    got = iou_3d(box(), box(y=0.5, yaw=math.pi / 4))[0, 0]
    assert got == pytest.approx(1.5 * octagon / (16 - 1.5 * octagon), abs=1e-12)


def test_height_offset_and_different_heights():
    # Same footprint 2×2, heights 2 (y ∈ [-1, 1]) and 4 (y ∈ [0, 4]): overlap 1 → 4 / (8 + 16 − 4).
    assert iou_3d(box(), box(y=2.0, ly=4.0))[0, 0] == pytest.approx(4 / 20, abs=1e-12)


def test_footprint_corners_are_counter_clockwise_with_kitti_yaw():
    c = bev_corners(box(lx=4, lz=2, yaw=math.pi / 2))[0]  # length now along −z
    area = 0.5 * sum(c[i, 0] * c[(i + 1) % 4, 1] - c[(i + 1) % 4, 0] * c[i, 1] for i in range(4))
    assert area == pytest.approx(8.0)
    assert np.ptp(c[:, 1]) == pytest.approx(4.0) and np.ptp(c[:, 0]) == pytest.approx(2.0)


def test_random_rotated_pairs_match_monte_carlo():
    rng = np.random.default_rng(0)
    a = np.concatenate([rng.uniform(-1, 1, (12, 3)), rng.uniform(1, 3, (12, 3)), rng.uniform(-np.pi, np.pi, (12, 1))], 1)
    b = a + np.concatenate([rng.uniform(-0.5, 0.5, (12, 3)), rng.uniform(-0.4, 0.4, (12, 3)), rng.uniform(-1, 1, (12, 1))], 1)
    full3d, fullbev = iou_3d(a, b), iou_bev(a, b)
    assert full3d.shape == (12, 12)
    assert np.all(np.diag(full3d) > 0.1)  # the pairs really overlap, so the comparison means something
    for i in range(12):
        mc = monte_carlo_iou(a[i], b[i], 50_000, rng)
        mc_bev = monte_carlo_iou(a[i], b[i], 50_000, rng, bev=True)
        assert full3d[i, i] == pytest.approx(mc, abs=0.015)
        assert fullbev[i, i] == pytest.approx(mc_bev, abs=0.015)
    # Pairwise entries equal the same computation done one pair at a time.
    for i, j in [(0, 5), (3, 3), (7, 2)]:
        assert full3d[i, j] == pytest.approx(iou_3d(a[i:i + 1], b[j:j + 1])[0, 0], abs=1e-12)


def test_symmetric_and_accepts_torch_and_empty():
    rng = np.random.default_rng(1)
    a = np.concatenate([rng.uniform(-2, 2, (6, 3)), rng.uniform(0.5, 3, (6, 3)), rng.uniform(-3, 3, (6, 1))], 1)
    np.testing.assert_allclose(iou_3d(a, a[::-1]), iou_3d(a[::-1], a).T, atol=1e-12)
    # Coincident edges everywhere (each box with itself) is the degenerate case for clipping.
    np.testing.assert_allclose(np.diag(iou_3d(a, a)), 1.0, atol=1e-9)
    np.testing.assert_allclose(iou_3d(torch.tensor(a), a), iou_3d(a, a))
    assert iou_3d(np.zeros((0, 7)), a).shape == (0, 6)
    assert iou_bev(a, np.zeros((0, 7))).shape == (6, 0)
    assert iou_3d(box(lx=0), box(lx=0))[0, 0] == 0.0  # degenerate boxes: 0, not NaN
    with pytest.raises(ShapeError):
        iou_3d(np.zeros((3, 6)), a)


def test_iou_across_frames_matches_the_exact_iou_where_both_apply():
    """Frames related by a rotation about Y plus a shift: boxes of b carried into a stay canonical, so the
    exact iou_3d is the reference for the lattice estimate."""
    import math

    from core.eval.iou3d import iou_3d, iou_3d_across_frames

    rng = np.random.default_rng(3)
    a_T_b = np.eye(4)
    ang = 0.4
    a_T_b[:3, :3] = [[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]]
    a_T_b[:3, 3] = [1.0, 0.2, -2.0]
    boxes_b = np.column_stack([rng.uniform(-2, 2, (6, 3)), rng.uniform(1, 4, (6, 3)), rng.uniform(-1, 1, 6)])
    centres_a = boxes_b[:, :3] @ a_T_b[:3, :3].T + a_T_b[:3, 3]
    boxes_b_in_a = np.column_stack([centres_a, boxes_b[:, 3:6], boxes_b[:, 6] + ang])   # the same boxes, in a
    boxes_a = boxes_b_in_a + np.column_stack([rng.uniform(-0.8, 0.8, (6, 3)), np.zeros((6, 3)), rng.uniform(-0.3, 0.3, 6)])
    exact = iou_3d(boxes_a, boxes_b_in_a)
    sampled = iou_3d_across_frames(boxes_a, boxes_b, a_T_b, samples_per_side=24)
    np.testing.assert_allclose(sampled, exact, atol=0.03)
    assert np.diag(exact).min() > 0.1                       # the test compares real overlaps, not zeros
    # a tilted relation (pitched 0.5 rad about the box's own centre): the box against itself tilted
    box = np.array([[0.0, 0.0, 5.0, 4.0, 1.5, 2.0, 0.3]])
    assert iou_3d_across_frames(box, box, np.eye(4))[0, 0] == pytest.approx(1.0)
    tilt = np.eye(4)
    tilt[:3, :3] = [[1, 0, 0], [0, math.cos(0.5), -math.sin(0.5)], [0, math.sin(0.5), math.cos(0.5)]]
    tilt[:3, 3] = box[0, :3] - tilt[:3, :3] @ box[0, :3]
    moved = iou_3d_across_frames(box, box, tilt)[0, 0]
    assert 0.3 < moved < 0.9                                # shares its centre, but the slabs cross
    assert iou_3d_across_frames(np.zeros((0, 7)), box, tilt).shape == (0, 1)
