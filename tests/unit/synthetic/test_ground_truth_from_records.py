"""core.data.ground_truth on generated and hand-built records: egomotion composes, occupancy/free space
against per-point loops, flow of static scenes and of one moving box against hand computation."""

import math

import numpy as np
import pytest
import torch

from core.data.ground_truth import gt_egomotion, gt_flow, gt_free, gt_moving_mask, gt_occupancy
from core.presets import TINY
from core.synthetic import default_world_config, generate_record
from synth_reference import yaw_matrix

GRID = TINY.grid  # 32×8×32 voxels of 1 m over x, z in [-16, 16], y in [-4, 4]


@pytest.fixture(scope="module")
def static_scene():
    torch.set_num_threads(1)
    world = default_world_config(TINY).with_overrides(moving_fraction=0.0)
    return generate_record(TINY, seed=3, moving_ego=True, num_frames=2, num_views=2, world=world)


def _pose(yaw: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = yaw_matrix(yaw)
    T[:3, 3] = t
    return T


def _hand_record(world_T_ref: np.ndarray, boxes_ref: np.ndarray, moving: bool) -> dict:
    """Minimal record: one camera at ref, one box given in ref (T×7) and moved into world by hand."""
    T = world_T_ref.shape[0]
    boxes = np.zeros((T, 2, 7), np.float32)
    for t in range(T):
        R, c = world_T_ref[t, :3, :3], world_T_ref[t, :3, 3]
        yaw = math.atan2(R[0, 2], R[0, 0])
        b = boxes_ref[t]
        boxes[t, 0] = [*(R @ b[:3] + c), *b[3:6], b[6] + yaw]
    return {
        "rgb": np.zeros((T, 1, 2, 2, 3), np.uint8), "depth": np.zeros((T, 1, 2, 2), np.float32),
        "pix_T_cam": np.eye(4, dtype=np.float32)[None], "world_T_cam": world_T_ref[:, None].astype(np.float32),
        "world_T_ref": world_T_ref.astype(np.float32), "boxes": boxes,
        "box_valid": np.array([[True, False]] * T), "box_id": np.array([1, -1], np.int32),
        "box_moving": np.array([moving, False]),
    }


def _centre(ix, iy, iz):
    """Voxel centre in ref (metres) of voxel (x, y, z) of the tiny grid."""
    v = GRID.voxel_size
    return np.array([GRID.xmin + (ix + 0.5) * v, GRID.ymin + (iy + 0.5) * v, GRID.zmin + (iz + 0.5) * v])


def test_egomotion_composes_with_world_T_ref(static_scene):
    r = static_scene
    ego = gt_egomotion(r, 0, 1)
    w0, w1 = r["world_T_ref"].astype(np.float64)
    assert np.allclose(w0 @ ego["ref0_T_ref1"].double().numpy(), w1, atol=1e-4)
    c0, c1 = r["world_T_cam"].astype(np.float64)
    assert np.allclose(c0 @ ego["cam0_T_cam1"].double().numpy(), c1, atol=1e-4)
    assert np.abs(ego["ref0_T_ref1"].numpy() - np.eye(4)).max() > 1e-2  # the ego did move
    assert torch.allclose(gt_egomotion(r, 1, 1)["ref0_T_ref1"], torch.eye(4), atol=1e-5)
    with pytest.raises(ValueError, match="out of range"):
        gt_egomotion(r, 0, 2)


def test_static_scene_flow_is_zero_when_stabilised_and_ego_motion_otherwise(static_scene):
    r = static_scene
    assert not r["box_moving"].any()
    flow = gt_flow(r, 0, GRID)
    assert flow.shape == (3, GRID.Z, GRID.Y, GRID.X) and flow.dtype == torch.float32
    assert float(flow.abs().max()) < 1e-4
    raw = gt_flow(r, 0, GRID, stabilised=False).numpy()
    ref1_T_ref0 = np.linalg.inv(r["world_T_ref"][1].astype(np.float64)) @ r["world_T_ref"][0]
    rng = np.random.default_rng(0)
    for ix, iy, iz in zip(rng.integers(0, GRID.X, 40), rng.integers(0, GRID.Y, 40), rng.integers(0, GRID.Z, 40)):
        p = _centre(ix, iy, iz)
        want = (ref1_T_ref0[:3, :3] @ p + ref1_T_ref0[:3, 3] - p) / GRID.voxel_size
        assert np.allclose(raw[:, iz, iy, ix], want, atol=1e-3)


@pytest.mark.parametrize("world_yaw", [0.0, 0.7])
def test_flow_of_one_moving_box_is_its_displacement(world_yaw):
    world_T_ref = np.stack([_pose(world_yaw, [5.0, 0.0, -3.0])] * 2)  # static ego, world ≠ ref
    # A 4×2×2 m box over voxel centres x ∈ {-1.5..1.5}, y ∈ {0.5, 1.5}, z ∈ {-0.5, 0.5}; it moves by
    # (1, 0, 2) m and turns 90° about its centre.
    b0 = np.array([0.0, 1.0, 0.0, 4.0, 2.0, 2.0, 0.0])
    b1 = np.array([1.0, 1.0, 2.0, 4.0, 2.0, 2.0, math.pi / 2])
    rec = _hand_record(world_T_ref, np.stack([b0, b1]), moving=True)
    flow = gt_flow(rec, 0, GRID).numpy()
    R = yaw_matrix(math.pi / 2)
    inside = np.zeros((GRID.Z, GRID.Y, GRID.X), bool)
    want = np.zeros_like(flow)
    for ix in range(GRID.X):
        for iy in range(GRID.Y):
            for iz in range(GRID.Z):
                p = _centre(ix, iy, iz)
                off = p - b0[:3]
                if (np.abs(off) <= b0[3:6] / 2).all():
                    inside[iz, iy, ix] = True
                    want[:, iz, iy, ix] = (R @ off + b1[:3] - p) / GRID.voxel_size
    assert np.abs(flow - want).max() < 1e-4
    assert inside.sum() == 4 * 2 * 2
    mask = gt_moving_mask(rec, 0, GRID).numpy()
    assert mask.shape == (1, GRID.Z, GRID.Y, GRID.X) and np.array_equal(mask[0] > 0, inside)
    rec["box_moving"][:] = False
    assert gt_moving_mask(rec, 0, GRID).sum() == 0


def test_occupancy_and_free_space_against_point_loops(static_scene):
    r, t, view = static_scene, 0, 1
    occ = gt_occupancy(r, t, GRID, views=[view])[0].numpy()
    K = r["pix_T_cam"][view].astype(np.float64)
    ref_T_cam = np.linalg.inv(r["world_T_ref"][t].astype(np.float64)) @ r["world_T_cam"][t, view]
    want = np.zeros_like(occ, dtype=bool)
    lo, v = np.array(GRID.bounds_min), GRID.voxel_size
    size = np.array([GRID.X, GRID.Y, GRID.Z])
    depth = r["depth"][t, view]
    ends, centre = [], ref_T_cam[:3, 3]
    Rc, tc = ref_T_cam[:3, :3].tolist(), ref_T_cam[:3, 3].tolist()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for i in range(depth.shape[0]):
        for j in range(depth.shape[1]):
            z = float(depth[i, j])
            if z <= 0:
                continue
            q = ((j - cx) / fx * z, (i - cy) / fy * z, z)
            p = [sum(Rc[r][k] * q[k] for k in range(3)) + tc[r] for r in range(3)]
            ijk = [math.floor((p[k] - lo[k]) / v) for k in range(3)]
            if all(0 <= ijk[k] < size[k] for k in range(3)):
                want[ijk[2], ijk[1], ijk[0]] = True
            ends.append(np.array(p))
    assert want.sum() > 50 and np.array_equal(occ > 0, want)

    free = gt_free(r, t, GRID, views=[view])[0].numpy()
    assert free.sum() > 50 and not ((free > 0) & (occ > 0)).any()
    # Halfway along a ray, the voxel is free unless something occupies it or it is the end point's voxel.
    checked = 0
    for p in ends[::37]:
        mid = centre + 0.5 * (p - centre)
        ijk = np.floor((mid - lo) / v).astype(int)
        end_ijk = np.floor((p - lo) / v).astype(int)
        if not ((ijk >= 0) & (ijk < size)).all() or (ijk == end_ijk).all() or occ[ijk[2], ijk[1], ijk[0]]:
            continue
        assert free[ijk[2], ijk[1], ijk[0]] == 1.0
        checked += 1
    assert checked > 10


def test_voxels_holding_only_a_moving_boxs_surface_move_with_it():
    """The rendered surface lies on the box's faces, so voxels holding it may have their centre just outside
    the box: they move with it when every depth point they hold is the box's (within the tolerance), and stay
    static when they also hold another surface (here a wall beside the box). Checked against a per-point
    loop over a hand-built record: one camera at ref looking along +z at a plane of depth 2.7 m, whose middle
    is the front face of a 3.2 × 3.2 × 2 m box that moves by (1, 0, 0.5) m."""
    from core.data.ground_truth import SURFACE_TOLERANCE_M, points_in_ref

    H = W = 24  # points 0.34 m apart on the plane: each rim voxel of the face holds wall points too
    world_T_ref = np.stack([_pose(0.4, [2.0, 0.0, -1.0])] * 2)
    b0 = np.array([0.0, 0.0, 3.7, 3.2, 3.2, 2.0, 0.0])  # front face z = 2.7; voxel z ∈ [2, 3) has centre 2.5
    b1 = b0 + np.array([1.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    rec = _hand_record(world_T_ref, np.stack([b0, b1]), moving=True)
    K = np.array([[8.0, 0, W / 2, 0], [0, 8.0, H / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    rec.update(rgb=np.zeros((2, 1, H, W, 3), np.uint8), depth=np.full((2, 1, H, W), 2.7, np.float32),
               pix_T_cam=K[None])
    flow = gt_flow(rec, 0, GRID).numpy()
    mask = gt_moving_mask(rec, 0, GRID).numpy()[0]

    # The slow reference: which box each point is on (a box grown by the tolerance), voxel by voxel.
    xyz, valid = points_in_ref(rec, 0)
    labels: dict[tuple, set] = {}
    lo, v = np.array(GRID.bounds_min), GRID.voxel_size
    for p in xyz.reshape(-1, 3)[valid.reshape(-1)].double().numpy():
        on_box = bool((np.abs(p - b0[:3]) <= b0[3:6] / 2 + SURFACE_TOLERANCE_M).all())
        ijk = tuple(int(k) for k in np.floor((p - lo) / v))
        labels.setdefault(ijk, set()).add(on_box)
    want = np.zeros_like(flow)
    moving = np.zeros(mask.shape, bool)
    for ix in range(GRID.X):
        for iy in range(GRID.Y):
            for iz in range(GRID.Z):
                p = _centre(ix, iy, iz)
                if (np.abs(p - b0[:3]) <= b0[3:6] / 2).all() or labels.get((ix, iy, iz)) == {True}:
                    moving[iz, iy, ix] = True
                    want[:, iz, iy, ix] = (b1[:3] - b0[:3]) / GRID.voxel_size
    surface_only = {k for k, s in labels.items() if s == {True}}
    mixed = {k for k, s in labels.items() if s == {True, False}}
    assert len(surface_only) == 4 and len(mixed) >= 4  # the face's middle 2×2 voxels; its rim beside the wall
    assert all(not (np.abs(_centre(*k) - b0[:3]) <= b0[3:6] / 2).all() for k in surface_only)  # centres outside
    assert np.abs(flow - want).max() < 1e-4 and np.array_equal(mask > 0, moving)
    rec["box_moving"][:] = False
    assert gt_moving_mask(rec, 0, GRID).sum() == 0
