"""Point-to-plane ICP recovers a known rigid transform of a synthetic structured cloud."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.baselines.icp import estimate_normals, icp_point_to_plane, voxel_downsample
from core.errors import ShapeError


def _scene(rng: np.random.Generator) -> np.ndarray:
    """Ground plane + two walls + a box: enough planes in all directions to constrain 6 DoF."""
    g = rng.uniform([-8, 0, -8], [8, 0, 8], size=(1500, 3)); g[:, 1] = 2.0
    w1 = rng.uniform([-8, -2, 6], [8, 2, 6], size=(800, 3))
    w2 = rng.uniform([-6, -2, -8], [-6, 2, 8], size=(800, 3))
    b = rng.uniform([1, 0, 1], [3, 2, 2], size=(600, 3)); b[:300, 0] = 1.0
    return np.concatenate([g, w1, w2, b])


def test_normals_of_plane_are_its_normal():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, size=(200, 3)); xyz[:, 1] = 0.5
    n = estimate_normals(xyz, neighbors=8)
    assert np.allclose(np.abs(n[:, 1]), 1.0, atol=1e-6)


@pytest.mark.parametrize("deg, trans", [(4.0, (0.4, -0.1, 0.6)), (0.0, (0.0, 0.0, 0.0))])
def test_icp_recovers_known_transform(deg, trans):
    rng = np.random.default_rng(1)
    target = _scene(rng)
    gt = np.eye(4)  # target_T_source
    gt[:3, :3] = Rotation.from_rotvec(np.deg2rad(deg) * np.array([0.2, 1.0, -0.1]) / np.linalg.norm([0.2, 1.0, -0.1])).as_matrix()
    gt[:3, 3] = trans
    source_T_target = np.linalg.inv(gt)
    source = target @ source_T_target[:3, :3].T + source_T_target[:3, 3]
    source = source + rng.normal(scale=0.005, size=source.shape)
    res = icp_point_to_plane(source, target, iterations=40, max_distance=2.0)
    err = np.linalg.inv(gt) @ res.target_T_source
    angle = np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))
    assert angle < np.deg2rad(0.2)
    assert np.linalg.norm(err[:3, 3]) < 0.03
    assert res.inlier_fraction > 0.9


def test_voxel_downsample_means():
    xyz = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.0, 0.0]])
    out = voxel_downsample(xyz, 1.0)
    assert sorted(map(tuple, np.round(out, 6))) == [(0.2, 0.2, 0.2), (1.5, 0.0, 0.0)]


def test_icp_rejects_bad_clouds():
    with pytest.raises(ShapeError):
        icp_point_to_plane(np.zeros((10, 2)), np.zeros((10, 3)))
    with pytest.raises(ShapeError):
        icp_point_to_plane(np.zeros((3, 3)), np.zeros((10, 3)))


def test_a_shrinking_gate_drops_the_wrong_matches_one_loose_gate_keeps():
    """A structured scene plus a block that moves on its own (a car between the frames): with one loose gate
    the block's points pull the pose off; the coarse-to-fine gates end within a tight gate of the true pose
    and leave the block out. The same points, the same 1 m first gate."""
    from core.baselines.icp import icp_coarse_to_fine

    rng = np.random.default_rng(3)
    scene = _scene(rng)
    gt = np.eye(4)  # target_T_source: the camera's motion
    gt[:3, :3] = Rotation.from_rotvec(np.deg2rad(1.5) * np.array([0.0, 1.0, 0.0])).as_matrix()
    gt[:3, 3] = (0.3, 0.0, 0.5)
    # the car's surface (a 2 × 1.5 × 2 m box's faces), in the target frame at t0
    lo, hi = np.array([-3.0, 0.5, -2.0]), np.array([-1.0, 2.0, 0.0])
    car = rng.uniform(lo, hi, size=(800, 3))
    face = rng.integers(0, 6, size=len(car))
    axis, side = face % 3, face // 3
    car[np.arange(len(car)), axis] = np.where(side == 0, lo[axis], hi[axis])
    target = np.concatenate([scene, car])
    source_T_target = np.linalg.inv(gt)
    moved_car = car + np.array([0.6, 0.0, 0.4])  # the car moved 0.72 m in the world meanwhile
    source = np.concatenate([scene, moved_car]) @ source_T_target[:3, :3].T + source_T_target[:3, 3]
    source = source + rng.normal(scale=0.005, size=source.shape)

    def errors(T):
        err = np.linalg.inv(gt) @ T
        return np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)), np.linalg.norm(err[:3, 3])

    loose = icp_point_to_plane(source, target, iterations=60, max_distance=1.0)
    staged = icp_coarse_to_fine(source, target, iterations=30, max_distances=(1.0, 0.5, 0.25))
    rot_loose, trans_loose = errors(loose.target_T_source)
    rot, trans = errors(staged.target_T_source)
    assert trans < 0.02 and rot < np.deg2rad(0.05)
    assert trans_loose > 3 * trans  # the loose gate alone is pulled toward the car's motion (0.10 m vs 0.004)
    assert staged.iterations >= 3
    with pytest.raises(ValueError, match="non-increasing"):
        icp_coarse_to_fine(source, target, max_distances=(0.25, 1.0))
