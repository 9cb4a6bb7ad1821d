"""The 2.5D moving-object baseline: 2D optical flow, thresholded, clustered, lifted to 3D with depth.

As the paper's baseline (§5, moving objects): estimate 2D optical flow between frames t and t+1
(OpenCV's Farneback here instead of PWC-Net; or the ground-truth 2D flow for the oracle variant),
threshold its magnitude, cluster the moving pixels into 2D connected components, lift each
component's pixels to 3D with the depth of frame t, keep the points near the component's median
depth (segmenting the point cloud), and fit an oriented box to them. The stabilised variant first
subtracts the flow the camera motion alone would induce on the static scene (given depth and the
relative pose). Only the visible surface is ever seen, so boxes fitted to it tend to be too small — the
weakness the paper points out. With a `size_prior` the boxes are completed as the 3D methods' are
(core.moving.amodal: oversized clusters split, each box grown to a whole object away from the camera and
down to the ground plane), so that a comparison of the two measures the flow, not the box fitting.

Conventions (docs/conventions.md#cameras-and-pixels): images H×W(×3), pixel centres at integer (u, v); 2D flow
H×W×2 in pixels (du, dv) from t to t+1; depth H×W metres along Z, 0 = missing; `pix_T_cam` 4×4; `cam1_T_cam0`
maps points of camera t into camera t+1; boxes canonical (x, y, z, lx, ly, lz, yaw). Inputs are one example
(no batch dimension), numpy or torch; outputs are numpy.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy import ndimage

from core.errors import ShapeError
from core.geometry import camera, se3
from core.geometry.boxes import box_T_obj, points_in_boxes
from core.moving.amodal import SizePrior, amodal_box, split_oversized
from core.moving.boxfit import fit_box_to_points
from core.moving.ground import DEFAULT_MARGIN_VOXELS, UP, ground_y_at
from core.moving.components import to_numpy
from core.moving.nms import nms_bev


def _gray(image) -> np.ndarray:
    img = to_numpy(image)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img.astype(np.uint8)), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise ShapeError(f"image: expected H×W×3 RGB or H×W gray, got {'×'.join(map(str, img.shape))}")
    return np.ascontiguousarray(img.astype(np.uint8))


def farneback_flow(rgb0, rgb1, *, pyr_scale: float = 0.5, levels: int = 3, winsize: int = 15,
                   iterations: int = 3, poly_n: int = 5, poly_sigma: float = 1.2) -> np.ndarray:
    """Dense 2D flow from frame t to t+1 by Farneback's method.

    rgb0, rgb1: H×W×3 uint8 RGB (or H×W gray). Returns H×W×2 float32 (du, dv) in pixels:
    the content at (u, v) in frame t is at (u + du, v + dv) in frame t+1.
    """
    g0, g1 = _gray(rgb0), _gray(rgb1)
    if g0.shape != g1.shape:
        raise ShapeError(f"frames differ in size: {g0.shape} vs {g1.shape}")
    return cv2.calcOpticalFlowFarneback(g0, g1, None, pyr_scale, levels, winsize, iterations, poly_n,
                                        poly_sigma, 0)


def _points_cam0(depth0, pix_T_cam):
    """depth H×W -> (xyz_cam0 (H·W)×3 float64 torch, valid (H·W) bool torch)."""
    d = torch.as_tensor(to_numpy(depth0), dtype=torch.float64)
    if d.dim() != 2:
        raise ShapeError(f"depth0: expected H×W, got {'×'.join(map(str, d.shape))}")
    K = torch.as_tensor(to_numpy(pix_T_cam), dtype=torch.float64).reshape(1, 4, 4)
    xyz, valid = camera.depth_to_points(d[None], K)              # 1×(H·W)×3, 1×(H·W)
    return xyz[0], valid[0]


def _flow_of_moved_points(xyz0: torch.Tensor, xyz1_cam1: torch.Tensor, valid: torch.Tensor,
                          pix_T_cam, H: int, W: int) -> np.ndarray:
    """Pixel displacement of points seen at xyz0 (cam0) and then at xyz1_cam1 (cam1): H×W×2."""
    K = torch.as_tensor(to_numpy(pix_T_cam), dtype=torch.float64).reshape(1, 4, 4)
    uv0, _ = camera.project(K, xyz0[None])                       # 1×N×2
    uv1, z1 = camera.project(K, xyz1_cam1[None])                 # 1×N×2, 1×N
    ok = valid & (z1[0] > camera.MIN_DEPTH)
    flow = torch.where(ok[:, None], uv1[0] - uv0[0], torch.zeros_like(uv0[0]))  # N×2
    return flow.reshape(H, W, 2).numpy().astype(np.float32)      # H×W×2


def camera_flow2d(depth0, pix_T_cam, cam1_T_cam0) -> np.ndarray:
    """2D flow the camera motion alone induces on a static scene. depth0 H×W, pix_T_cam 4×4,
    cam1_T_cam0 4×4 -> H×W×2 (du, dv) pixels; 0 where depth is missing or the point leaves the front."""
    H, W = to_numpy(depth0).shape
    xyz0, valid = _points_cam0(depth0, pix_T_cam)
    T = torch.as_tensor(to_numpy(cam1_T_cam0), dtype=torch.float64).reshape(1, 4, 4)
    return _flow_of_moved_points(xyz0, se3.apply(T, xyz0[None])[0], valid, pix_T_cam, H, W)


def oracle_flow2d(depth0, pix_T_cam, cam1_T_cam0, boxes0_cam0, boxes1_cam0) -> np.ndarray:
    """Ground-truth 2D flow: camera motion plus rigid object motion.

    A point of frame t inside box k (boxes0_cam0 K×7, canonical, in cam0) moves with the box to
    boxes1_cam0[k] (the same object at t+1, still expressed in cam0): p' = box1_T_obj · box0_T_obj⁻¹ · p;
    other points are static. Then everything is seen from camera t+1. Returns H×W×2 pixels.
    """
    H, W = to_numpy(depth0).shape
    xyz0, valid = _points_cam0(depth0, pix_T_cam)
    b0 = torch.as_tensor(to_numpy(boxes0_cam0), dtype=torch.float64).reshape(1, -1, 7)
    b1 = torch.as_tensor(to_numpy(boxes1_cam0), dtype=torch.float64).reshape(1, -1, 7)
    moved = xyz0.clone()
    if b0.shape[1]:
        inside = points_in_boxes(xyz0[None], b0)[0]                        # N×K
        motion = se3.compose(box_T_obj(b1)[0], se3.invert(box_T_obj(b0)[0]))  # K×4×4 in cam0
        owner = torch.where(inside.any(1), inside.float().argmax(1), -1)  # N: first box holding it
        for k in range(b0.shape[1]):
            sel = owner == k
            if sel.any():
                moved[sel] = se3.apply(motion[k:k + 1], xyz0[sel][None])[0]
    T = torch.as_tensor(to_numpy(cam1_T_cam0), dtype=torch.float64).reshape(1, 4, 4)
    return _flow_of_moved_points(xyz0, se3.apply(T, moved[None])[0], valid, pix_T_cam, H, W)


def moving_objects_from_flow2d(flow2d, depth0, pix_T_cam, *, threshold: float, min_pixels: int,
                               stabilise: bool = False, cam1_T_cam0=None, ref_T_cam0=None,
                               depth1=None, dt: float = 1.0, depth_tolerance: float = 1.0,
                               surround_px: int = 4, nms_iou: float = 0.3, size_prior: SizePrior | None = None,
                               ground: np.ndarray | None = None, point_scale: float = 0.5,
                               ground_margin: float | None = DEFAULT_MARGIN_VOXELS) -> list[dict]:
    """Scored 3D boxes of the moving regions of a 2D flow field.

    flow2d: H×W×2 pixels (t → t+1), depth0: H×W (frame t), pix_T_cam: 4×4. threshold: flow
    magnitude (pixels) above which a pixel moves; min_pixels: smaller clusters are dropped.
    stabilise: subtract `camera_flow2d(depth0, pix_T_cam, cam1_T_cam0)` first (needs cam1_T_cam0).
    ref_T_cam0: 4×4 frame the boxes are returned in (default: ref = cam0). depth1: H×W depth of
    frame t+1, used to measure 3D velocity (else velocity is NaN). depth_tolerance: metres around a
    cluster's median depth that its points may lie within. surround_px: width of the 2D
    center-surround ring. size_prior: complete each box to a whole object (core.moving.amodal, as the 3D
    methods do; None: the visible points' box), with `ground` (4,) the ground plane in ref (None: the visible
    vertical extent) and `point_scale` (metres) the scale amodal_box reads the points at (the 3D methods'
    voxel size). ground_margin: with `ground`, pixels whose point lies less than this many `point_scale`s
    above the plane (or below it) do not move, as the 3D methods' voxels within `MovingBoxesConfig.ground_margin`
    of it do not (core.pipeline.moving_boxes); None: no such gate. Why: a 2D flow method's smooth flow spills
    from an object's base onto the road around it, which then joins its cluster and widens its box — the 3D
    methods drop those points, so the comparison should too.

    Returns a list, best score first, of dicts: `box_ref` (7,), `score` (2D center-surround: moving
    fraction of the cluster's bounding rectangle minus that of the ring around it, in [−1, 1]),
    `velocity_ref` (3,) m/s, `num_pixels`.
    """
    flow = to_numpy(flow2d).astype(np.float64)
    depth = to_numpy(depth0).astype(np.float64)
    H, W = depth.shape
    if flow.shape != (H, W, 2):
        raise ShapeError(f"flow2d: expected {H}×{W}×2 to match depth0, got {'×'.join(map(str, flow.shape))}")
    if stabilise:
        if cam1_T_cam0 is None:
            raise ValueError("stabilise=True needs cam1_T_cam0 (the camera motion to subtract)")
        flow = flow - camera_flow2d(depth, pix_T_cam, cam1_T_cam0)
    valid = np.isfinite(depth) & (depth > 0)
    moving = (np.linalg.norm(flow, axis=-1) > threshold) & valid              # H×W
    xyz0, _ = _points_cam0(depth, pix_T_cam)
    xyz0 = xyz0.numpy().reshape(H, W, 3)                                     # H×W×3 cam0
    ref_T_cam = np.eye(4) if ref_T_cam0 is None else to_numpy(ref_T_cam0).astype(np.float64).reshape(4, 4)
    if ground is not None and ground_margin is not None:
        plane = to_numpy(ground).astype(np.float64).reshape(4)
        plane = plane if plane[:3] @ UP >= 0 else -plane                     # normal up (fit_ground_plane's sign)
        xyz_ref = xyz0 @ ref_T_cam[:3, :3].T + ref_T_cam[:3, 3]              # H×W×3 ref
        height = xyz_ref @ plane[:3] + plane[3]                              # H×W metres above the plane
        moving &= height >= ground_margin * point_scale
    labels, count = ndimage.label(moving, structure=np.ones((3, 3)))
    cam0_T_cam1 = None if cam1_T_cam0 is None else np.linalg.inv(to_numpy(cam1_T_cam0).astype(np.float64).reshape(4, 4))
    found = []
    for k, region in enumerate(ndimage.find_objects(labels), start=1):
        mask = labels == k
        if mask.sum() < min_pixels:
            continue
        z = depth[mask]
        near = np.abs(z - np.median(z)) <= depth_tolerance                  # segment the point cloud
        if near.sum() < max(3, min_pixels // 2):
            continue
        pts_cam = xyz0[mask][near]                                           # P×3
        pts_ref = pts_cam @ ref_T_cam[:3, :3].T + ref_T_cam[:3, 3]
        score = _center_surround_2d(moving, region, surround_px)
        velocity = np.full(3, np.nan)
        if depth1 is not None:
            velocity = _velocity(flow2d, to_numpy(depth1), pix_T_cam, mask, near, pts_cam, cam0_T_cam1, dt,
                                 depth_tolerance)
            velocity = ref_T_cam[:3, :3] @ velocity
        for box in _boxes(pts_ref, size_prior, ground, point_scale, viewpoint=ref_T_cam[:3, 3]):
            found.append(dict(box_ref=box, score=score, velocity_ref=velocity, num_pixels=int(mask.sum())))
    if not found:
        return []
    keep = nms_bev(np.stack([d["box_ref"] for d in found]), np.array([d["score"] for d in found]), nms_iou)
    return [found[i] for i in keep]


def _boxes(pts_ref: np.ndarray, size_prior: SizePrior | None, ground: np.ndarray | None, point_scale: float, *,
           viewpoint: np.ndarray) -> list[np.ndarray]:
    """A cluster's lifted points P×3 (ref) -> its boxes: the visible points' box, or with a size prior the
    amodal box of each piece that fits it (core.moving.detect_moving's rule for a component)."""
    if size_prior is None:
        return [fit_box_to_points(pts_ref)]
    pieces, _ = split_oversized(pts_ref, size_prior, voxel=point_scale, pad=0.0)
    boxes = []
    for index in pieces:
        piece = pts_ref[index]
        centre = fit_box_to_points(piece)[:3]
        boxes.append(amodal_box(piece, viewpoint=viewpoint, prior=size_prior, voxel=point_scale, pad=0.0,
                                ground_y=None if ground is None else ground_y_at(ground, centre[0], centre[2])))
    return boxes


def _center_surround_2d(moving: np.ndarray, region: tuple, surround_px: int) -> float:
    """Moving fraction inside the cluster's bounding rectangle minus that of the ring around it."""
    H, W = moving.shape
    rows, cols = region
    inner = moving[rows, cols].mean()
    r0, r1 = max(rows.start - surround_px, 0), min(rows.stop + surround_px, H)
    c0, c1 = max(cols.start - surround_px, 0), min(cols.stop + surround_px, W)
    outer = moving[r0:r1, c0:c1]
    ring_count = outer.size - moving[rows, cols].size
    ring = (outer.sum() - moving[rows, cols].sum()) / ring_count if ring_count else 0.0
    return float(inner - ring)


def _velocity(flow2d, depth1, pix_T_cam, mask, near, pts_cam0, cam0_T_cam1, dt: float,
              depth_tolerance: float) -> np.ndarray:
    """Median 3D displacement / dt of a cluster's points, by following the raw flow into depth1.

    Points of frame t+1 are brought back to cam0 with cam0_T_cam1 when known (camera motion
    removed), otherwise compared in camera coordinates as they are. Returns 3 (m/s, cam0 axes).
    """
    H, W = depth1.shape
    flow = to_numpy(flow2d).astype(np.float64)
    v, u = np.nonzero(mask)
    v, u = v[near], u[near]
    u1f, v1f = u + flow[v, u, 0], v + flow[v, u, 1]                  # where the flow says they went
    u1 = np.clip(np.rint(u1f).astype(int), 0, W - 1)
    v1 = np.clip(np.rint(v1f).astype(int), 0, H - 1)
    z1 = depth1[v1, u1]                                               # depth there (nearest pixel)
    # Flow that lands off the object (blurred flow at its silhouette) jumps in depth: drop it.
    ok = np.isfinite(z1) & (z1 > 0) & (np.abs(z1 - pts_cam0[:, 2]) <= depth_tolerance)
    if not ok.any():
        return np.full(3, np.nan)
    K = to_numpy(pix_T_cam).astype(np.float64).reshape(4, 4)
    p1 = np.stack([(u1f[ok] - K[0, 2]) / K[0, 0] * z1[ok], (v1f[ok] - K[1, 2]) / K[1, 1] * z1[ok], z1[ok]], axis=-1)
    if cam0_T_cam1 is not None:
        p1 = p1 @ cam0_T_cam1[:3, :3].T + cam0_T_cam1[:3, 3]
    return np.median(p1 - pts_cam0[ok], axis=0) / dt  # median: robust to the remaining strays


def moving_objects_2p5d(rgb0, rgb1, depth0, pix_T_cam, *, threshold: float, min_pixels: int,
                        flow2d=None, **options) -> list[dict]:
    """The whole 2.5D baseline on one frame pair: Farneback flow (or the given `flow2d`, e.g.
    `oracle_flow2d(...)` for the oracle variant), then `moving_objects_from_flow2d(..., **options)`."""
    flow = farneback_flow(rgb0, rgb1) if flow2d is None else flow2d
    return moving_objects_from_flow2d(flow, depth0, pix_T_cam, threshold=threshold, min_pixels=min_pixels, **options)
