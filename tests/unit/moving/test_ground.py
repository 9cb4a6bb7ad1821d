"""core.moving.ground: the RANSAC plane against planes built by hand, and voxel heights against a
per-voxel loop."""

import math

import numpy as np
import pytest

from core.geometry.grid import GridConfig
from core.moving.ground import above_ground, fit_ground_plane, voxel_heights

GRID = GridConfig(xmin=-4.0, xmax=4.0, ymin=-2.0, ymax=2.0, zmin=-4.0, zmax=4.0, Z=8, Y=4, X=8)


def _ground_points(rng, n, *, height=1.5, tilt_deg=0.0):
    """n points on the plane y = height + tan(tilt)·x (y down), over 20×20 m."""
    x, z = rng.uniform(-10, 10, n), rng.uniform(-10, 10, n)
    return np.stack([x, height + math.tan(math.radians(tilt_deg)) * x, z], axis=1)


def test_recovers_a_tilted_ground_among_clutter():
    rng = np.random.default_rng(0)
    ground = _ground_points(rng, 3000, height=1.5, tilt_deg=5.0)
    wall = np.stack([np.full(1500, 3.0), rng.uniform(-3, 1.5, 1500), rng.uniform(-10, 10, 1500)], axis=1)
    boxes = rng.uniform([-2, -1, -2], [2, 1.5, 2], size=(1500, 3))  # cars, poles: off the plane
    plane = fit_ground_plane(np.concatenate([ground, wall, boxes]))
    assert plane is not None
    n, d = plane[:3], plane[3]
    assert abs(np.linalg.norm(n) - 1) < 1e-9 and n[1] < 0  # unit, pointing up (−y)
    expected = np.array([math.sin(math.radians(5.0)), -math.cos(math.radians(5.0)), 0.0])  # normal of y = h + tan·x
    assert np.allclose(n, expected, atol=1e-3)
    assert abs(plane @ np.array([0.0, 1.5, 0.0, 1.0])) < 1e-3  # (0, 1.5, 0) lies on it
    assert abs(d - 1.5 * math.cos(math.radians(5.0))) < 1e-3    # the origin is 1.5·cos(5°) above it


def test_no_ground_when_only_walls_or_planes_above_the_rig():
    rng = np.random.default_rng(1)
    wall = np.stack([np.full(2000, 3.0), rng.uniform(-3, 1.5, 2000), rng.uniform(-10, 10, 2000)], axis=1)
    assert fit_ground_plane(wall) is None                  # vertical: tilted beyond max_tilt_deg
    ceiling = _ground_points(rng, 2000, height=-2.5)        # horizontal but above the origin
    assert fit_ground_plane(ceiling) is None
    assert fit_ground_plane(np.zeros((0, 3))) is None and fit_ground_plane(np.full((100, 3), np.nan)) is None


def test_deterministic_for_a_seed():
    rng = np.random.default_rng(2)
    pts = np.concatenate([_ground_points(rng, 2000), rng.uniform(-5, 5, (2000, 3))])
    assert np.array_equal(fit_ground_plane(pts, seed=3), fit_ground_plane(pts, seed=3))


def test_voxel_heights_match_a_loop_and_above_ground_keeps_the_margin():
    plane = np.array([0.1, -math.sqrt(1 - 0.01 - 0.04), 0.2, 1.0])
    heights = voxel_heights(GRID, plane)
    assert heights.shape == (GRID.Z, GRID.Y, GRID.X)
    v = GRID.voxel_size
    for z in range(GRID.Z):
        for y in range(GRID.Y):
            for x in range(GRID.X):
                centre = np.array([GRID.xmin + (x + 0.5) * v, GRID.ymin + (y + 0.5) * v, GRID.zmin + (z + 0.5) * v])
                assert heights[z, y, x] == pytest.approx(plane[:3] @ centre + plane[3])
    keep = above_ground(GRID, plane, margin_voxels=0.5)
    assert np.array_equal(keep, heights >= 0.5 * v) and keep.any() and not keep.all()
    assert above_ground(GRID, None) is None


def test_a_ground_on_a_voxel_face_keeps_the_voxel_above_it():
    """The synthetic world's ground lies exactly on a voxel face (y = 2 with 1 m voxels): a fitted plane
    carries rounding, and the voxel above the face must survive it at the default margin."""
    rng = np.random.default_rng(4)
    grid = GridConfig(xmin=-16.0, xmax=16.0, ymin=-4.0, ymax=4.0, zmin=-16.0, zmax=16.0, Z=32, Y=8, X=32)
    plane = fit_ground_plane(_ground_points(rng, 5000, height=2.0) + rng.normal(0, 1e-3, (5000, 3)))
    keep = above_ground(grid, plane)   # layers' centres: y = -3.5 ... 3.5; layer 5 (y 1.5) is 0.5 above
    assert keep[:, :6].all() and not keep[:, 6:].any()
