"""boxes: corners, points_in_boxes against a loop, transforms, KITTI round trip."""

import math

import pytest
import torch

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.boxes import (NotYawRotationError, box_corners, box_T_obj, boxes_to_kitti, kitti_to_boxes,
                                 points_in_boxes, transform_boxes)

D = torch.float64


def _random_boxes(B: int, K: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(B, K, 3, generator=g, dtype=D) * 3
    size = torch.rand(B, K, 3, generator=g, dtype=D) * 3 + 0.5
    yaw = (torch.rand(B, K, 1, generator=g, dtype=D) * 2 - 1) * math.pi
    return torch.cat([c, size, yaw], -1)


def test_corners_of_a_known_box():
    # length 4 along x, height 2, width 1; yaw 90° turns the length axis to −z
    box = torch.tensor([[[1.0, 2.0, 3.0, 4.0, 2.0, 1.0, math.pi / 2]]], dtype=D)
    corners = box_corners(box)[0, 0]
    lo, hi = corners.amin(0), corners.amax(0)
    assert torch.allclose(lo, torch.tensor([0.5, 1.0, 1.0], dtype=D), atol=1e-12)
    assert torch.allclose(hi, torch.tensor([1.5, 3.0, 5.0], dtype=D), atol=1e-12)
    assert (corners[:4, 1] < corners[4:, 1]).all()  # top face first (Y down)
    # corner 1 is (+lx/2, −ly/2, −lz/2) in obj: +x of the object turned to −z
    assert torch.allclose(corners[1], torch.tensor([1.0 - 0.5, 1.0, 3.0 - 2.0], dtype=D), atol=1e-12)


def test_box_T_obj_maps_unit_corners_to_corners():
    boxes = _random_boxes(2, 3, 0)
    T = box_T_obj(boxes)
    signs = torch.tensor([[-1, -1, -1], [1, -1, -1], [1, -1, 1], [-1, -1, 1],
                          [-1, 1, -1], [1, 1, -1], [1, 1, 1], [-1, 1, 1]], dtype=D)
    corners = box_corners(boxes)
    for b in range(2):
        for k in range(3):
            local = 0.5 * signs * boxes[b, k, 3:6]
            assert torch.allclose(se3.apply(T[b, k][None], local[None])[0], corners[b, k], atol=1e-12)


def test_points_in_boxes_matches_loop(device):
    boxes = _random_boxes(2, 4, 1)
    g = torch.Generator().manual_seed(2)
    xyz = torch.randn(2, 300, 3, generator=g, dtype=D) * 3
    got = points_in_boxes(xyz.to(device), boxes.to(device)).cpu()
    hits = 0
    for b in range(2):
        for k in range(4):
            c, l, yaw = boxes[b, k, :3], boxes[b, k, 3:6], boxes[b, k, 6].item()
            cs, sn = math.cos(yaw), math.sin(yaw)
            for n in range(300):
                dx, dy, dz = (xyz[b, n] - c).tolist()
                # inverse yaw rotation written out: R^T = [[c,0,−s],[0,1,0],[s,0,c]]
                lx, ly, lz = cs * dx - sn * dz, dy, sn * dx + cs * dz
                inside = abs(lx) <= l[0] / 2 and abs(ly) <= l[1] / 2 and abs(lz) <= l[2] / 2
                hits += inside
                assert bool(got[b, n, k]) == inside
    assert hits > 5


def test_transform_boxes_moves_corners_rigidly():
    boxes_b = _random_boxes(3, 5, 3)
    g = torch.Generator().manual_seed(4)
    yaw = (torch.rand(3, generator=g, dtype=D) * 2 - 1) * math.pi
    a_T_b = se3.from_rt(se3.yaw_to_matrix(yaw), torch.randn(3, 3, generator=g, dtype=D))
    boxes_a = transform_boxes(a_T_b, boxes_b)
    assert (boxes_a[..., 6].abs() <= math.pi + 1e-12).all()
    corners_from_b = se3.apply(a_T_b, box_corners(boxes_b).reshape(3, -1, 3)).reshape(3, 5, 8, 3)
    assert torch.allclose(box_corners(boxes_a), corners_from_b, atol=1e-10)
    back = transform_boxes(se3.invert(a_T_b), boxes_a)
    assert torch.allclose(box_corners(back), box_corners(boxes_b), atol=1e-10)


def test_transform_boxes_rejects_pitch():
    T = se3.from_rt(se3.euler_to_matrix(torch.tensor([0.2], dtype=D), torch.zeros(1, dtype=D), torch.zeros(1, dtype=D)),
                    torch.zeros(1, 3, dtype=D))
    with pytest.raises(NotYawRotationError, match="not about Y"):
        transform_boxes(T, _random_boxes(1, 2, 5))


def test_kitti_round_trip_and_bottom_centre():
    boxes = _random_boxes(2, 6, 6)
    kitti = boxes_to_kitti(boxes)
    assert torch.allclose(kitti_to_boxes(kitti), boxes, atol=1e-15)
    # KITTI's bottom centre is the mean of the 4 bottom corners (largest y, since Y points down)
    bottom = box_corners(boxes)[..., 4:, :].mean(-2)
    assert torch.allclose(kitti[..., 3:6], bottom, atol=1e-12)
    assert torch.equal(kitti[..., 0], boxes[..., 4]) and torch.equal(kitti[..., 1], boxes[..., 5])
    assert torch.equal(kitti[..., 2], boxes[..., 3])
    # a KITTI label line: h w l x y z ry
    car = torch.tensor([[1.5, 1.6, 3.9, 2.0, 1.7, 10.0, 0.3]], dtype=D)
    assert torch.allclose(kitti_to_boxes(car), torch.tensor([[2.0, 0.95, 10.0, 3.9, 1.5, 1.6, 0.3]], dtype=D))


def test_bad_box_shape():
    with pytest.raises(ShapeError, match="boxes"):
        box_corners(torch.zeros(1, 2, 6))
