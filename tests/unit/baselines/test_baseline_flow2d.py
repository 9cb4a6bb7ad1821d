"""The 2.5D moving-object baseline on synthetic image pairs with a translated textured square."""

import numpy as np
import pytest
from scipy import ndimage

from core.baselines.flow2d import (camera_flow2d, farneback_flow, moving_objects_2p5d,
                                   moving_objects_from_flow2d, oracle_flow2d)

H, W, F = 72, 96, 60.0
K = np.array([[F, 0, (W - 1) / 2, 0], [0, F, (H - 1) / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
SQUARE = (slice(24, 44), slice(30, 50))  # rows v 24..43, cols u 30..49
SHIFT_U = 4                              # pixels the square moves right


def texture(seed, shape):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.uniform(0, 255, shape), 2.0)


def image_pair():
    """Static textured background at 10 m, a textured square at 5 m shifted SHIFT_U px to the right."""
    bg, fg = texture(0, (H, W)), texture(1, (H, W))
    img0, img1 = bg.copy(), bg.copy()
    img0[SQUARE] = fg[SQUARE]
    moved = (SQUARE[0], slice(SQUARE[1].start + SHIFT_U, SQUARE[1].stop + SHIFT_U))
    img1[moved] = fg[SQUARE]
    rgb = [np.repeat(np.clip(i, 0, 255).astype(np.uint8)[..., None], 3, axis=-1) for i in (img0, img1)]
    depth0 = np.full((H, W), 10.0)
    depth0[SQUARE] = 5.0
    depth1 = np.full((H, W), 10.0)
    depth1[moved] = 5.0
    return rgb[0], rgb[1], depth0, depth1


def square_points():
    """Slow reference: the square's pixels lifted to cam0 at 5 m."""
    v, u = np.mgrid[SQUARE]
    return np.stack([(u - K[0, 2]) / F * 5.0, (v - K[1, 2]) / F * 5.0, np.full(u.shape, 5.0)], -1).reshape(-1, 3)


def test_farneback_sees_the_square_move():
    rgb0, rgb1, _, _ = image_pair()
    flow = farneback_flow(rgb0, rgb1)
    assert flow.shape == (H, W, 2)
    inner = flow[28:40, 34:46]  # well inside the square
    assert np.median(inner[..., 0]) == pytest.approx(SHIFT_U, abs=0.75)
    assert np.median(np.abs(flow[:, :15])) < 0.2  # the background far from the square is still


def test_farneback_baseline_finds_the_translated_square():
    rgb0, rgb1, depth0, depth1 = image_pair()
    found = moving_objects_2p5d(rgb0, rgb1, depth0, K, threshold=1.5, min_pixels=30, depth1=depth1, dt=0.5)
    assert len(found) == 1
    box = found[0]["box_ref"]
    pts = square_points()
    centre = 0.5 * (pts.min(0) + pts.max(0))
    # The box lies on the square (a flat fragment at 5 m) and spans roughly its 1.6 m × 1.6 m.
    assert np.abs(box[[0, 1]] - centre[[0, 1]]).max() < 0.35 and box[2] == pytest.approx(5.0, abs=0.1)
    assert max(box[3], box[5]) == pytest.approx(np.ptp(pts[:, 0]), abs=0.4)
    assert box[4] == pytest.approx(np.ptp(pts[:, 1]), abs=0.4)
    # 4 px at 5 m with f = 60 is 1/3 m per 0.5 s, along +x. Farneback's flow fades towards the
    # square's edges (its windows straddle them), so the cluster's median speed comes out low.
    vx, vy, vz = found[0]["velocity_ref"]
    assert 0.5 * (4 * 5.0 / F / 0.5) < vx < 1.2 * (4 * 5.0 / F / 0.5)
    assert abs(vy) < 0.1 and abs(vz) < 0.1


def test_oracle_flow_is_exact_and_recovers_the_square():
    _, _, depth0, depth1 = image_pair()
    pts = square_points()
    shift_m = SHIFT_U * 5.0 / F
    lo, hi = pts.min(0) - 1e-6, pts.max(0) + 1e-6
    box0 = np.concatenate([(lo + hi) / 2, hi - lo + [0, 0.02, 0.02], [0.0]])[None]
    box1 = box0 + [[shift_m, 0, 0, 0, 0, 0, 0]]
    flow = oracle_flow2d(depth0, K, np.eye(4), box0, box1)
    np.testing.assert_allclose(flow[SQUARE][..., 0], SHIFT_U, atol=1e-9)
    assert np.abs(flow[:, :25]).max() == 0.0
    found = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30, depth1=depth1, dt=1.0)
    assert len(found) == 1
    box = found[0]["box_ref"]
    np.testing.assert_allclose(box[:3], (pts.min(0) + pts.max(0)) / 2, atol=1e-6)
    np.testing.assert_allclose(found[0]["velocity_ref"], [shift_m, 0, 0], atol=1e-6)
    assert found[0]["score"] == pytest.approx(1.0)


def test_stabilisation_removes_the_camera_motion():
    _, _, depth0, _ = image_pair()
    cam1_T_cam0 = np.eye(4)
    cam1_T_cam0[0, 3] = -0.3  # the camera moves 0.3 m right: the static scene shifts left in the image
    pts = square_points()
    lo, hi = pts.min(0) - 1e-6, pts.max(0) + 1e-6
    box0 = np.concatenate([(lo + hi) / 2, hi - lo + [0, 0.02, 0.02], [0.0]])[None]
    box1 = box0 + [[0.6, 0, 0, 0, 0, 0, 0]]
    flow = oracle_flow2d(depth0, K, cam1_T_cam0, box0, box1)
    ego = camera_flow2d(depth0, K, cam1_T_cam0)
    np.testing.assert_allclose(ego[:, :20, 0], -0.3 * F / 10.0)  # slow reference: −t·f/z at 10 m
    # Unstabilised, the whole background (1.8 px of apparent motion) passes a 1 px threshold.
    raw = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30)
    assert any(d["box_ref"][2] > 9.0 for d in raw)
    stable = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30, stabilise=True,
                                        cam1_T_cam0=cam1_T_cam0)
    assert len(stable) == 1
    np.testing.assert_allclose(stable[0]["box_ref"][:3], (pts.min(0) + pts.max(0)) / 2, atol=1e-6)
    with pytest.raises(ValueError, match="cam1_T_cam0"):
        moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30, stabilise=True)


def test_a_size_prior_completes_the_lifted_face_as_the_3d_methods_do():
    """The square is the visible face of a larger object: with a size prior the box is the 3D methods' amodal
    box of the same lifted points (core.moving.amodal) — grown away from the camera, down to the ground — and
    without one the face's own thin box."""
    from core.moving.amodal import SizePrior, amodal_box

    _, _, depth0, depth1 = image_pair()
    pts = square_points()
    shift_m = SHIFT_U * 5.0 / F
    lo, hi = pts.min(0) - 1e-6, pts.max(0) + 1e-6
    box0 = np.concatenate([(lo + hi) / 2, hi - lo + [0, 0.02, 0.02], [0.0]])[None]
    flow = oracle_flow2d(depth0, K, np.eye(4), box0, box0 + [[shift_m, 0, 0, 0, 0, 0, 0]])
    prior = SizePrior.from_size(4.0, 2.0, 2.5)
    ground = np.array([0.0, 1.0, 0.0, -2.0])  # y = 2 m below the camera (y down)
    (visible,) = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30)
    (whole,) = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30, size_prior=prior,
                                          ground=ground, point_scale=0.5)
    want = amodal_box(pts, viewpoint=np.zeros(3), prior=prior, voxel=0.5, pad=0.0, ground_y=2.0)
    np.testing.assert_allclose(whole["box_ref"], want, atol=1e-9)
    box = whole["box_ref"]
    half_depth = 0.5 * (box[3] * abs(np.sin(box[6])) + box[5] * abs(np.cos(box[6])))  # bird's-eye extent along z
    assert box[2] - half_depth == pytest.approx(5.0, abs=0.05)                 # its near face is the square
    assert box[2] > visible["box_ref"][2] + 0.5                                 # it grew away from the camera
    assert box[1] + 0.5 * box[4] == pytest.approx(2.0, abs=1e-6)                # and stands on the ground
    assert whole["score"] == visible["score"]


def test_flow_spilling_onto_the_ground_is_gated_as_the_3d_methods_ground_voxels_are():
    """Rows below the square see a floor 2 m under the camera; flow that spills onto it moves no box when the
    ground plane is given (the 3D methods drop voxels within a quarter voxel of it), while the square standing
    above it is still found. The slow reference: each floor pixel's lifted point lies on the plane (height 0)."""
    _, _, depth0, _ = image_pair()
    floor_rows = slice(50, H)
    v = np.arange(H, dtype=float)[floor_rows, None]
    depth0[floor_rows] = 2.0 * F / (v - K[1, 2])            # the ray of row v meets y = 2 m at this depth
    lifted_y = (v - K[1, 2]) / F * depth0[floor_rows]
    np.testing.assert_allclose(lifted_y, 2.0)
    flow = np.zeros((H, W, 2))
    flow[56:66, 10:40, 0] = 3.0                             # a patch of floor "moving" (Farneback's spill)
    flow[SQUARE + (0,)] = SHIFT_U
    for ground in (np.array([0.0, -1.0, 0.0, 2.0]), np.array([0.0, 1.0, 0.0, -2.0])):   # either sign of the plane
        gated = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30, ground=ground)
        assert len(gated) == 1 and gated[0]["box_ref"][2] == pytest.approx(5.0, abs=0.1)   # the square only
    ungated = moving_objects_from_flow2d(flow, depth0, K, threshold=1.0, min_pixels=30,
                                         ground=np.array([0.0, -1.0, 0.0, 2.0]), ground_margin=None)
    assert len(ungated) == 2
