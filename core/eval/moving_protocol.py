"""The moving-object evaluation protocol on records (paper §5, "moving objects"): ground truth, camera
setting, and the 2.5D baselines run over every view of a rig.

Frames (docs/conventions.md#frames): `ref_t` is the record's `world_T_ref[t]`; boxes are canonical rows
(x, y, z, lx, ly, lz, yaw) in ref_t; 2D flow is H×W×2 pixels (du, dv) from t to t+1. A record is the
dict of numpy arrays of docs/data.md#records.

Ground truth of a pair (t, t+1): the objects flagged `box_moving` that are valid at both steps, whose
centre at t lies in the grid and that at least `min_points` depth points of the rig (all views, step t)
fall in — an object nobody sees, or that lies outside the map, cannot be found by any method here.
"""

from __future__ import annotations

import numpy as np
import torch

from core.baselines.flow2d import farneback_flow, moving_objects_from_flow2d
from core.data.ground_truth import SURFACE_TOLERANCE_M, gt_egomotion, points_in_ref
from core.geometry import camera, se3
from core.geometry.boxes import box_T_obj, points_in_boxes, transform_boxes
from core.geometry.grid import GridConfig
from core.geometry.poses import relative
from core.moving.nms import nms_bev

# Relative ego motion below this counts as a static camera (metres / radians per step).
STATIC_TRANSLATION_M = 1e-3
STATIC_ROTATION_RAD = 1e-4


def camera_setting(record, t: int) -> str:
    """"static" if the rig does not move from t to t+1 (gt_egomotion), else "moving"."""
    T = gt_egomotion(record, t, t + 1)["ref0_T_ref1"].double()
    moved = (float(T[:3, 3].norm()) > STATIC_TRANSLATION_M
             or float(se3.rotation_angle(T[None, :3, :3])[0]) > STATIC_ROTATION_RAD)
    return "moving" if moved else "static"


def gt_moving_boxes(record, t: int, grid: GridConfig, *, min_points: int = 10) -> np.ndarray:
    """Ground-truth moving objects of the pair (t, t+1) in ref_t: G×7 float64 (see the module doc)."""
    valid = np.asarray(record["box_valid"][t]) & np.asarray(record["box_valid"][t + 1]) \
        & np.asarray(record["box_moving"]).astype(bool)
    rows = np.flatnonzero(valid)
    if len(rows) == 0:
        return np.zeros((0, 7))
    ref_T_world = se3.invert(torch.as_tensor(np.asarray(record["world_T_ref"][t:t + 1]), dtype=torch.float64))
    boxes = transform_boxes(ref_T_world, torch.as_tensor(np.asarray(record["boxes"][t:t + 1, rows]),
                                                         dtype=torch.float64))           # 1×G×7 in ref_t
    lo, hi = torch.tensor(grid.bounds_min, dtype=torch.float64), torch.tensor(grid.bounds_max, dtype=torch.float64)
    inside = ((boxes[0, :, :3] >= lo) & (boxes[0, :, :3] < hi)).all(-1)                # G
    xyz, ok = points_in_ref(record, t)                                                  # V×N×3, V×N
    pts = xyz.double().reshape(1, -1, 3)[:, ok.reshape(-1)]                             # 1×P×3
    seen = points_in_boxes(pts, boxes)[0].sum(0) >= min_points                          # G
    return boxes[0, inside & seen].numpy()


def oracle_flow2d_rig(record, t: int, view: int) -> np.ndarray:
    """Ground-truth 2D flow of one view from t to t+1: H×W×2 pixels.

    Each depth point of step t is moved rigidly with the object box (world frame) holding it,
    p' = box_{t+1} · box_t⁻¹ · p, static otherwise (a point within SURFACE_TOLERANCE_M of a box belongs to it, as
    in the 3D ground truth), and projected into the same view at t+1. (The
    world frame is used because a rig camera is pitched: boxes are only yaw-rotated in gravity-aligned
    frames, so they cannot be expressed in the camera frame as core.baselines.flow2d.oracle_flow2d needs.)
    """
    depth = torch.as_tensor(np.asarray(record["depth"][t, view]), dtype=torch.float64)   # H×W
    H, W = depth.shape
    K = torch.as_tensor(np.asarray(record["pix_T_cam"][view]), dtype=torch.float64)[None]  # 1×4×4
    world_T_cam0 = torch.as_tensor(np.asarray(record["world_T_cam"][t, view]), dtype=torch.float64)[None]
    world_T_cam1 = torch.as_tensor(np.asarray(record["world_T_cam"][t + 1, view]), dtype=torch.float64)[None]
    xyz0, valid = camera.depth_to_points(depth[None], K)                                 # 1×N×3, 1×N
    pw = se3.apply(world_T_cam0, xyz0)                                                  # 1×N×3 world
    rows = np.flatnonzero(np.asarray(record["box_valid"][t]) & np.asarray(record["box_valid"][t + 1]))
    moved = pw.clone()
    if len(rows):
        b0 = torch.as_tensor(np.asarray(record["boxes"][t:t + 1, rows]), dtype=torch.float64)      # 1×K×7
        b1 = torch.as_tensor(np.asarray(record["boxes"][t + 1:t + 2, rows]), dtype=torch.float64)  # 1×K×7
        # grown by the tolerance the 3D ground truth uses (core.data.ground_truth._surface_membership): rendered
        # surfaces lie on the box faces, and round-off put ~10 % of a mover's pixels just outside an exact box,
        # where they kept zero flow
        grown = b0.clone()
        grown[..., 3:6] += 2.0 * SURFACE_TOLERANCE_M
        inside = points_in_boxes(pw, grown)[0]                                          # N×K
        motion = se3.compose(box_T_obj(b1)[0], se3.invert(box_T_obj(b0)[0]))            # K×4×4
        owner = torch.where(inside.any(1), inside.float().argmax(1), -1)                 # N
        for k in range(len(rows)):
            sel = owner == k
            if bool(sel.any()):
                moved[0, sel] = se3.apply(motion[k:k + 1], pw[:, sel])[0]
    uv0, _ = camera.project(K, xyz0)                                                    # 1×N×2
    uv1, z1 = camera.project(K, se3.apply(se3.invert(world_T_cam1), moved))            # 1×N×2, 1×N
    ok = valid[0] & (z1[0] > camera.MIN_DEPTH)
    flow = torch.where(ok[:, None], uv1[0] - uv0[0], torch.zeros_like(uv0[0]))          # N×2
    return flow.reshape(H, W, 2).numpy().astype(np.float32)                             # H×W×2


def moving_objects_2p5d_rig(record, t: int, *, flow_source: str, stabilise: bool, threshold_px: float,
                            min_pixels: int, dt: float, nms_iou: float = 0.3,
                            grid: GridConfig | None = None, size_prior=None,
                            ground: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The 2.5D baseline (core.baselines.flow2d) on every view of the pair (t, t+1), boxes lifted to
    ref_t and merged across views by BEV NMS. flow_source: "farneback" or "oracle" (ground-truth 2D
    flow); stabilise: subtract the flow the camera motion induces (with the true relative pose);
    grid: keep only boxes whose centre lies in it — the region the ground truth (`gt_moving_boxes`) and
    the 3D methods' boxes cover, so that a right detection beyond the map is not a false positive.
    size_prior / ground: amodal boxes as the 3D methods' (core.baselines.flow2d; needs `grid`, whose voxel
    size is the points' scale); None: the visible points' boxes.

    Returns (boxes D×7 in ref_t, scores D), best first.
    """
    if flow_source not in ("farneback", "oracle"):
        raise ValueError(f"flow_source must be 'farneback' or 'oracle', got {flow_source!r}")
    world_T_ref = torch.as_tensor(np.asarray(record["world_T_ref"][t]), dtype=torch.float64)
    boxes, scores = [], []
    for v in range(record["rgb"].shape[1]):
        world_T_cam0 = torch.as_tensor(np.asarray(record["world_T_cam"][t, v]), dtype=torch.float64)
        world_T_cam1 = torch.as_tensor(np.asarray(record["world_T_cam"][t + 1, v]), dtype=torch.float64)
        if flow_source == "farneback":
            flow = farneback_flow(record["rgb"][t, v], record["rgb"][t + 1, v])
        else:
            flow = oracle_flow2d_rig(record, t, v)
        found = moving_objects_from_flow2d(
            flow, record["depth"][t, v], record["pix_T_cam"][v], threshold=threshold_px, min_pixels=min_pixels,
            stabilise=stabilise, cam1_T_cam0=relative(world_T_cam1, world_T_cam0).numpy(),
            ref_T_cam0=relative(world_T_ref, world_T_cam0).numpy(), dt=dt, nms_iou=nms_iou,
            size_prior=size_prior, ground=ground, point_scale=0.5 if grid is None else grid.voxel_size)
        boxes += [d["box_ref"] for d in found]
        scores += [d["score"] for d in found]
    if not boxes:
        return np.zeros((0, 7)), np.zeros(0)
    boxes_arr, scores_arr = np.stack(boxes), np.asarray(scores, dtype=np.float64)
    if grid is not None:
        inside = ((boxes_arr[:, :3] >= grid.bounds_min) & (boxes_arr[:, :3] < grid.bounds_max)).all(-1)
        boxes_arr, scores_arr = boxes_arr[inside], scores_arr[inside]
        if not len(boxes_arr):
            return np.zeros((0, 7)), np.zeros(0)
    keep = nms_bev(boxes_arr, scores_arr, nms_iou)
    return boxes_arr[keep], scores_arr[keep]
