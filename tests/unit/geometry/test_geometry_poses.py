"""core.geometry.poses: relative poses from world poses (p_a = a_T_b @ p_b), on random rigid poses."""

import torch

from core.geometry import se3
from core.geometry.poses import camera_centres, relative, rig_cam_T_ref


def _poses(*shape: int, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    n = int(torch.tensor(shape).prod())
    return se3.random_rigid(n, 1.0, 3.0, gen, dtype=torch.float64).reshape(*shape, 4, 4)


def test_relative_maps_points_of_b_into_a():
    world_T_a, world_T_b = _poses(5, seed=1), _poses(5, seed=2)
    a_T_b = relative(world_T_a, world_T_b)
    p_b = torch.randn(5, 7, 3, dtype=torch.float64)
    torch.testing.assert_close(se3.apply(world_T_a, se3.apply(a_T_b, p_b)), se3.apply(world_T_b, p_b))
    torch.testing.assert_close(relative(world_T_a, world_T_a), torch.eye(4, dtype=torch.float64).expand(5, 4, 4))


def test_rig_cam_T_ref_defaults_to_view_0_and_centres_are_camera_positions():
    world_T_cam, world_T_ref = _poses(2, 3, seed=3), _poses(2, seed=4)
    cam_T_ref = rig_cam_T_ref(world_T_cam, world_T_ref)                      # 2×3×4×4
    torch.testing.assert_close(cam_T_ref, relative(world_T_cam, world_T_ref[:, None]))
    torch.testing.assert_close(rig_cam_T_ref(world_T_cam, None)[:, 0], torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
    centres = camera_centres(cam_T_ref)                                       # 2×3×3, in ref
    torch.testing.assert_close(se3.apply(world_T_ref, centres), world_T_cam[..., :3, 3])


def _camera(yaw: float, pitch: float, roll: float, t=(1.0, -2.0, 3.0)) -> torch.Tensor:
    """world_T_cam = [R_yaw(ψ) · R_x(pitch) · R_z(roll) | t] (Y down: positive pitch about x looks down)."""
    from core.geometry import se3

    zero = torch.tensor(0.0, dtype=torch.float64)
    R_x = se3.euler_to_matrix(torch.tensor(pitch, dtype=torch.float64), zero, zero)
    R_z = se3.euler_to_matrix(zero, zero, torch.tensor(roll, dtype=torch.float64))
    R = se3.yaw_to_matrix(torch.tensor(yaw, dtype=torch.float64)) @ R_x @ R_z
    return se3.from_rt(R, torch.tensor(t, dtype=torch.float64))


def test_levelled_keeps_position_and_heading_and_drops_pitch_and_roll():
    """Against a brute-force search: the level frame's Z is the horizontal direction closest to the camera's
    optical axis (1e-4 rad steps around the answer), Y is world Y, the origin the camera centre."""
    from core.geometry import se3
    from core.geometry.poses import levelled

    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        yaw, pitch, roll = ((torch.rand(3, generator=gen, dtype=torch.float64) * 2 - 1)
                            * torch.tensor([3.1, 1.0, 0.5], dtype=torch.float64)).tolist()
        world_T_cam = _camera(yaw, pitch, roll)
        world_T_level = levelled(world_T_cam)
        assert se3.is_rigid(world_T_level.float())
        torch.testing.assert_close(world_T_level[:3, 3], world_T_cam[:3, 3])
        torch.testing.assert_close(world_T_level[:3, 1], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        forward = world_T_cam[:3, 2]
        candidates = torch.linspace(-torch.pi, torch.pi, 62833, dtype=torch.float64)  # 1e-4 rad steps
        z_axes = torch.stack([candidates.sin(), torch.zeros_like(candidates), candidates.cos()], -1)
        best = candidates[(z_axes @ forward).argmax()]
        got = se3.matrix_to_yaw(world_T_level[:3, :3])
        assert abs(float(se3.wrap_angle(got - best))) < 2e-4
        assert abs(float(se3.wrap_angle(got - torch.tensor(yaw, dtype=torch.float64)))) < 1e-9  # R_x, R_z keep it


def test_levelled_of_a_camera_looking_straight_down_takes_the_heading_from_its_x_axis():
    from core.geometry import se3
    from core.geometry.poses import levelled

    world_T_cam = _camera(0.7, torch.pi / 2, 0.0)  # optical axis along world +Y (down)
    got = se3.matrix_to_yaw(levelled(world_T_cam)[:3, :3])
    assert abs(float(got) - 0.7) < 1e-9
    batch = torch.stack([_camera(0.3, 0.2, 0.1), world_T_cam])  # 2×4×4: leading dims are kept
    assert levelled(batch).shape == (2, 4, 4)
    torch.testing.assert_close(levelled(batch)[1], levelled(world_T_cam))


def test_level_over_ground_moves_the_levelled_frame_ahead_and_onto_the_ground_height():
    """The placed frame has the levelled frame's axes; its origin is `ahead` metres along the heading and
    `origin_height` above the ground plane y = ground_y (Y down); without ground_y, at the camera's height."""
    from core.geometry.poses import level_over_ground, levelled

    torch.manual_seed(3)
    world_T_cam = se3.random_rigid(6, 0.6, 5.0, torch.Generator().manual_seed(3), dtype=torch.float64)
    base = levelled(world_T_cam)
    placed = level_over_ground(world_T_cam, ahead=16.0, ground_y=2.0, origin_height=2.0)
    torch.testing.assert_close(placed[:, :3, :3], base[:, :3, :3])
    for i in range(6):
        centre = world_T_cam[i, :3, 3]
        forward = world_T_cam[i, :3, 2].clone()
        forward[1] = 0.0  # the optical axis on the horizontal plane, by hand
        forward = forward / forward.norm()
        expected = centre + 16.0 * forward
        expected[1] = 0.0  # 2 m above the ground at y = 2 (Y down)
        torch.testing.assert_close(placed[i, :3, 3], expected)
    kept_height = level_over_ground(world_T_cam, ahead=3.0)
    torch.testing.assert_close(kept_height[:, 1, 3], world_T_cam[:, 1, 3])
    torch.testing.assert_close(level_over_ground(world_T_cam), base)
