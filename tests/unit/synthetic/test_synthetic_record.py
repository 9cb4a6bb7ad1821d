"""generate_record: the record contract, determinism, objects in bounds, sensor options, and geometric
consistency of the rendered views (against slow per-pixel references)."""

import itertools

import numpy as np
import pytest
import torch

from core.data.record import RECORD_KEYS, RECORD_SCHEMA, validate_record
from core.presets import TINY
from core.synthetic import default_world_config, generate_record
from synth_reference import nearest_hit, yaw_matrix


@pytest.fixture(scope="module")
def rec():
    torch.set_num_threads(1)
    return generate_record(TINY, seed=0, moving_ego=True, num_frames=3)


def test_keys_dtypes_shapes(rec):
    assert set(rec) == set(RECORD_KEYS)
    for key, (dtype, _) in RECORD_SCHEMA.items():
        assert rec[key].dtype == dtype, key
    dims = validate_record(rec, "synthetic seed 0")
    K = default_world_config(TINY).max_objects
    assert dims == {"T": 3, "V": TINY.num_views, "H": TINY.camera.H, "W": TINY.camera.W, "K": K}
    small = generate_record(TINY, seed=1, num_views=1, num_frames=1)
    assert validate_record(small, "synthetic seed 1")["T"] == 1 and small["rgb"].shape[1] == 1
    # Padding rows: invalid at every step, id -1, not moving, zero boxes.
    n = int(rec["box_valid"][0].sum())
    assert n >= 1 and (rec["box_valid"].sum(0) == np.where(np.arange(K) < n, 3, 0)).all()
    assert (rec["box_id"][:n] > 0).all() and len(set(rec["box_id"][:n])) == n and (rec["box_id"][n:] == -1).all()
    assert not rec["box_moving"][n:].any() and not rec["boxes"][:, n:].any()


def test_deterministic_by_seed(rec):
    again = generate_record(TINY, seed=0, moving_ego=True, num_frames=3)
    for key in RECORD_KEYS:
        assert np.array_equal(rec[key], again[key]), key
    other = generate_record(TINY, seed=1, moving_ego=True, num_frames=3, num_views=1)
    assert not np.array_equal(rec["world_T_cam"][:, :1], other["world_T_cam"])


def _corners(box):
    """8×3 corners of one box, by hand."""
    R = yaw_matrix(float(box[6]))
    signs = np.array(list(itertools.product((-0.5, 0.5), repeat=3)))
    return (signs * box[3:6]) @ R.T + box[:3]


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_some_object_inside_grid_at_every_step(seed):
    r = generate_record(TINY, seed=seed, moving_ego=True, num_frames=4, num_views=1)
    g = TINY.grid
    lo, hi = np.array(g.bounds_min), np.array(g.bounds_max)
    for t in range(4):
        ref_T_world = np.linalg.inv(r["world_T_ref"][t].astype(np.float64))
        inside = []
        for k in np.flatnonzero(r["box_valid"][t]):
            c = _corners(r["boxes"][t, k].astype(np.float64)) @ ref_T_world[:3, :3].T + ref_T_world[:3, 3]
            inside.append(bool(((c >= lo) & (c <= hi)).all()))
        assert any(inside), f"seed {seed} step {t}: no object inside the grid"


def test_reference_frame_is_gravity_aligned_and_ground_at_ground_y(rec):
    R = rec["world_T_ref"][:, :3, :3]
    assert np.allclose(R[:, 1], [0, 1, 0], atol=1e-6) and np.allclose(R[:, :, 1], [0, 1, 0], atol=1e-6)
    # The ego moved: the ref frames differ between steps.
    assert np.abs(rec["world_T_ref"][2, :3, 3] - rec["world_T_ref"][0, :3, 3]).max() > 0.1
    # Depth points in ref: nothing below the ground, and a good share of points on it.
    t, v = 1, 0
    K = rec["pix_T_cam"][v].astype(np.float64)
    ref_T_cam = np.linalg.inv(rec["world_T_ref"][t].astype(np.float64)) @ rec["world_T_cam"][t, v]
    ii, jj = np.nonzero(rec["depth"][t, v])
    z = rec["depth"][t, v, ii, jj].astype(np.float64)
    xyz = np.stack([(jj - K[0, 2]) / K[0, 0] * z, (ii - K[1, 2]) / K[1, 1] * z, z], -1)
    y_ref = xyz @ ref_T_cam[1, :3] + ref_T_cam[1, 3]
    assert y_ref.max() <= TINY.ground_y + 1e-3
    assert (np.abs(y_ref - TINY.ground_y) < 1e-2).mean() > 0.2


def test_sparse_depth_keeps_lidar_rows_and_noise_perturbs_returns():
    cfg = default_world_config(TINY)
    dense = generate_record(TINY, seed=5, num_views=1, num_frames=1)["depth"]
    sparse = generate_record(TINY, seed=5, num_views=1, num_frames=1, sparse_depth=True)["depth"]
    rows = np.flatnonzero((sparse[0, 0] > 0).any(-1))
    assert len(rows) > 3 and ((rows - cfg.sparse_row_step // 2) % cfg.sparse_row_step == 0).all()
    kept = sparse > 0
    assert np.array_equal(sparse[kept], dense[kept])  # sparsity drops returns, never moves them
    assert kept.sum() < 0.3 * (dense > 0).sum()
    noisy = generate_record(TINY, seed=5, num_views=1, num_frames=1, noise=0.05)["depth"]
    assert np.array_equal(noisy == 0, dense == 0)
    diff = (noisy - dense)[dense > 0]
    assert 0.035 < diff.std() < 0.065 and abs(diff.mean()) < 0.01


def test_views_of_one_record_agree_geometrically(rec):
    """Points unprojected from view a's depth, moved into view b, land where b sees the same depth
    (unless b sees something nearer: occlusion). A slow per-pixel loop is the reference."""
    t, H, W = 0, TINY.camera.H, TINY.camera.W
    max_depth = default_world_config(TINY).max_depth
    for a, b in [(0, 1), (1, 2), (2, 0)]:
        Ka, Kb = rec["pix_T_cam"][a].astype(np.float64), rec["pix_T_cam"][b].astype(np.float64)
        b_T_a = np.linalg.inv(rec["world_T_cam"][t, b].astype(np.float64)) @ rec["world_T_cam"][t, a]
        depth_a, depth_b = rec["depth"][t, a], rec["depth"][t, b]
        agree = occluded = contradict = 0
        for i in range(0, H, 2):
            for j in range(0, W, 2):
                z = float(depth_a[i, j])
                if z <= 0:
                    continue
                p_a = np.array([(j - Ka[0, 2]) / Ka[0, 0] * z, (i - Ka[1, 2]) / Ka[1, 1] * z, z])
                p_b = b_T_a[:3, :3] @ p_a + b_T_a[:3, 3]
                if p_b[2] <= 0.1 or p_b[2] > max_depth - 5:
                    continue
                u, v = Kb[0, 0] * p_b[0] / p_b[2] + Kb[0, 2], Kb[1, 1] * p_b[1] / p_b[2] + Kb[1, 2]
                iu, iv = int(round(u)), int(round(v))
                if not (1 <= iu < W - 1 and 1 <= iv < H - 1):
                    continue
                near = depth_b[iv - 1:iv + 2, iu - 1:iu + 2].astype(np.float64)
                near = np.where(near > 0, near, np.inf)  # no return = nothing there
                tol = 0.05 + 0.02 * p_b[2]
                if np.abs(near - p_b[2]).min() <= tol:
                    agree += 1
                elif near[1, 1] < p_b[2]:
                    occluded += 1
                else:
                    contradict += 1
        visible = agree + contradict
        assert agree > 200, (a, b, agree)
        assert agree / visible > 0.97, (a, b, agree, occluded, contradict)


def test_rendered_depth_matches_single_ray_reference_on_boxes():
    """Without static structures, every pixel's depth is the nearest of ground and the record's boxes."""
    world = default_world_config(TINY).with_overrides(num_buildings=(0, 0), num_walls=(0, 0), num_poles=(0, 0))
    r = generate_record(TINY, seed=7, num_frames=2, num_views=2, world=world)
    max_depth = world.max_depth
    on_box = bad = 0
    for t, v in [(0, 0), (1, 1)]:
        K, P = r["pix_T_cam"][v].astype(np.float64), r["world_T_cam"][t, v].astype(np.float64)
        boxes = r["boxes"][t][r["box_valid"][t]].astype(np.float64)
        for i in range(0, TINY.camera.H, 2):
            for j in range(0, TINY.camera.W, 2):
                d = np.array([(j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1], 1.0])
                want, which = nearest_hit(P[:3, 3], P[:3, :3] @ d, boxes, TINY.ground_y)
                want = want if want <= max_depth else 0.0
                got = float(r["depth"][t, v, i, j])
                on_box += which >= 0
                bad += abs(got - want) > 1e-3 * max(want, 1.0)
    assert on_box > 100
    assert bad <= 3, bad
