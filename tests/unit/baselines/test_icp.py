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
