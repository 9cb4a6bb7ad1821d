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
