"""se3: float64 round trips between rotation parameterisations and 4×4 algebra."""

import math

import pytest
import torch

from core.errors import ShapeError
from core.geometry import se3

D = torch.float64


def _random_rotations(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return se3.random_rigid(n, math.pi, 0.0, g, dtype=D)[:, :3, :3]


def _slow_euler(rx: float, ry: float, rz: float) -> torch.Tensor:
    """R = Rz·Ry·Rx written out one elementary rotation at a time."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=D)
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=D)
    Rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=D)
    return Rz @ Ry @ Rx


def test_random_rotations_are_rigid_and_angle_bounded():
    g = torch.Generator().manual_seed(1)
    T = se3.random_rigid(64, 0.3, 2.0, g, dtype=D)
    assert se3.is_rigid(T, 1e-10).all()
    assert (se3.rotation_angle(T[:, :3, :3]) <= 0.3 + 1e-12).all()
    assert (T[:, :3, 3].abs() <= 2.0).all()
    # same seed -> same transforms
    assert torch.equal(T, se3.random_rigid(64, 0.3, 2.0, torch.Generator().manual_seed(1), dtype=D))


def test_is_rigid_rejects_non_rigid():
    T = torch.eye(4, dtype=D).repeat(4, 1, 1)
    T[1, 0, 0] = 2.0  # scale
    T[2, 3, 0] = 0.5  # bad bottom row
    T[3, :3, :3] = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=D))  # reflection
    assert se3.is_rigid(T).tolist() == [True, False, False, False]


def test_axis_angle_round_trip_and_rodrigues():
    R = _random_rotations(200)
    aa = se3.matrix_to_axis_angle(R)
    assert torch.allclose(se3.axis_angle_to_matrix(aa), R, atol=1e-12)
    # angle of the axis-angle vector matches rotation_angle; near 0 and π too
    assert torch.allclose(aa.norm(dim=-1), se3.rotation_angle(R), atol=1e-12)
    for angle in (0.0, 1e-9, math.pi - 1e-7, math.pi):
        v = torch.tensor([[0.3, -0.5, 0.8]], dtype=D)
        v = v / v.norm() * angle
        R1 = se3.axis_angle_to_matrix(v)
        assert torch.allclose(se3.axis_angle_to_matrix(se3.matrix_to_axis_angle(R1)), R1, atol=1e-9)


def test_quaternion_round_trip():
    R = _random_rotations(200, seed=2)
    q = se3.matrix_to_quaternion(R)
    assert torch.allclose(q.norm(dim=-1), torch.ones(200, dtype=D))
    assert (q[:, 0] >= 0).all()
    assert torch.allclose(se3.quaternion_to_matrix(q), R, atol=1e-12)
    # (w, x, y, z) order: a quarter turn about Z is (cos 45°, 0, 0, sin 45°)
    qz = torch.tensor([[math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]], dtype=D)
    expected = torch.tensor([[[0, -1, 0], [1, 0, 0], [0, 0, 1]]], dtype=D)
    assert torch.allclose(se3.quaternion_to_matrix(qz), expected, atol=1e-15)


def test_euler_matches_slow_composition_and_round_trips():
    g = torch.Generator().manual_seed(3)
    angles = (torch.rand(50, 3, generator=g, dtype=D) * 2 - 1) * torch.tensor([math.pi, math.pi / 2, math.pi], dtype=D)
    R = se3.euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2])
    for i in range(50):
        assert torch.allclose(R[i], _slow_euler(*angles[i].tolist()), atol=1e-14)
    rx, ry, rz = se3.matrix_to_euler(R)
    assert torch.allclose(torch.stack([rx, ry, rz], -1), angles, atol=1e-9)
    # gimbal lock still rebuilds R
    Rl = se3.euler_to_matrix(torch.tensor([0.4], dtype=D), torch.tensor([math.pi / 2], dtype=D), torch.tensor([0.1], dtype=D))
    assert torch.allclose(se3.euler_to_matrix(*se3.matrix_to_euler(Rl)), Rl, atol=1e-9)


def test_yaw_matrix_convention_and_round_trip():
    yaw = torch.linspace(-3.1, 3.1, 13, dtype=D)
    R = se3.yaw_to_matrix(yaw)
    assert torch.allclose(R, se3.euler_to_matrix(torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)), atol=1e-15)
    assert torch.allclose(se3.matrix_to_yaw(R), yaw, atol=1e-14)
    # positive yaw turns +x toward -z
    assert torch.allclose(se3.yaw_to_matrix(torch.tensor(math.pi / 2, dtype=D)) @ torch.tensor([1.0, 0, 0], dtype=D),
                          torch.tensor([0.0, 0, -1], dtype=D), atol=1e-15)


def test_invert_compose_apply():
    g = torch.Generator().manual_seed(4)
    a_T_b = se3.random_rigid(8, math.pi, 5.0, g, dtype=D)
    b_T_c = se3.random_rigid(8, math.pi, 5.0, g, dtype=D)
    eye = torch.eye(4, dtype=D).expand(8, 4, 4)
    assert torch.allclose(se3.compose(se3.invert(a_T_b), a_T_b), eye, atol=1e-12)
    assert torch.allclose(se3.compose(a_T_b, se3.invert(a_T_b)), eye, atol=1e-12)
    assert torch.allclose(se3.invert(a_T_b), torch.linalg.inv(a_T_b), atol=1e-12)
    xyz = torch.randn(8, 10, 3, generator=g, dtype=D)
    via_two = se3.apply(a_T_b, se3.apply(b_T_c, xyz))
    assert torch.allclose(se3.apply(se3.compose(a_T_b, b_T_c), xyz), via_two, atol=1e-12)
    homo = torch.cat([xyz, torch.ones(8, 10, 1, dtype=D)], -1) @ a_T_b.transpose(1, 2)
    assert torch.allclose(se3.apply(a_T_b, xyz), homo[..., :3], atol=1e-12)
    R, t = se3.split_rt(a_T_b)
    assert torch.equal(se3.from_rt(R, t), a_T_b)


def test_wrap_angle():
    a = torch.tensor([0.0, math.pi, -math.pi, 3 * math.pi / 2, -7.0], dtype=D)
    w = se3.wrap_angle(a)
    assert (w > -math.pi).all() and (w <= math.pi + 1e-15).all()
    assert torch.allclose(torch.cos(w), torch.cos(a)) and torch.allclose(torch.sin(w), torch.sin(a), atol=1e-12)


def test_bad_shapes_raise():
    with pytest.raises(ShapeError, match="a_T_b"):
        se3.invert(torch.eye(3))
    with pytest.raises(ShapeError, match="xyz_b"):
        se3.apply(torch.eye(4)[None], torch.zeros(1, 5, 2))


def test_axis_angle_gradient_finite_at_zero():
    v = torch.zeros(1, 3, dtype=D, requires_grad=True)
    se3.axis_angle_to_matrix(v).sum().backward()
    assert torch.isfinite(v.grad).all()
    assert torch.autograd.gradcheck(se3.axis_angle_to_matrix, (torch.tensor([[0.3, -0.2, 0.5]], dtype=D, requires_grad=True),))
