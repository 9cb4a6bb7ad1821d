"""Unsupervised moving-object detection on the test set: our 3D flow pipeline vs the 2.5D baseline.

Each test record contributes its pair (0, 1), filed under "static" or "moving" camera by its true
egomotion. Ground truth: the boxes valid at step 0 whose object moves (`box_moving`), in ref0, centre
inside the grid, oriented (the paper fits oriented boxes to its segments). AP at 3D IoU `iou`
(all-point) with PR curves, per camera setting and method:

- `<arm>, GT egomotion`: core.pipeline.moving_objects(stabilize="poses") over the flow bundle of a
  pretraining arm (the paper's model and its RGB-regression counterpart);
- `<arm>, egomotion module`: the same, stabilised with the trained egomotion module (moving camera);
- `2.5D Farneback`, `2.5D Farneback stabilised` (camera-induced flow from the true relative pose
  subtracted) and `2.5D oracle flow` (true 2D flow from the boxes' motion, stabilised; `true_flow2d`): core.baselines.flow2d per view,
  boxes lifted to ref0, merged over the views with bird's-eye NMS.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch

from core.baselines.flow2d import farneback_flow, moving_objects_from_flow2d
from core.eval.average_precision import APAccumulator
from core.eval.iou3d import iou_3d
from core.geometry import camera, se3
from core.geometry.boxes import box_T_obj, points_in_boxes
from core.moving.nms import nms_bev
from core.pipeline.moving import moving_objects
from core.tasks.detector import gt_boxes_ref
from services.cli.eval_tasks.common import pair_inputs, record_batch

SETTINGS = ("static", "moving")
CURVE_POINTS = 50   # points kept per PR curve in metrics.json (for the plots)


def camera_moves(record: dict, t0: int = 0, t1: int = 1, *, eps: float = 1e-4) -> bool:
    """Whether the map frame (anchored to the ego) moves between t0 and t1."""
    w = torch.as_tensor(record["world_T_ref"], dtype=torch.float64)
    rel = se3.invert(w[t0:t0 + 1]) @ w[t1:t1 + 1]                               # 1×4×4 ref0_T_ref1
    return bool((rel[0] - torch.eye(4, dtype=torch.float64)).abs().max() > eps)


def moving_gt_ref0(record: dict, grid) -> np.ndarray:
    """G×7 oriented boxes of the moving objects at step 0, in ref0, centre inside the grid."""
    batch = {"boxes": torch.as_tensor(record["boxes"])[None], "box_valid": torch.as_tensor(record["box_valid"])[None],
             "world_T_ref": torch.as_tensor(record["world_T_ref"])[None]}
    boxes_ref, keep = gt_boxes_ref(batch, 0, grid)                               # 1×K×7, 1×K
    keep = keep[0] & torch.as_tensor(record["box_moving"]).bool()
    return boxes_ref[0, keep].double().numpy()


def baseline_2p5d(record: dict, *, variant: str, threshold: float, min_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """The 2.5D baseline over every view of the pair (0, 1): boxes D×7 in ref0 and scores D."""
    rgb, depth = record["rgb"], record["depth"]                                  # T×V×H×W×3, T×V×H×W
    pix = record["pix_T_cam"].astype(np.float64)                                 # V×4×4
    w_cam = record["world_T_cam"].astype(np.float64)                             # T×V×4×4
    ref0_T_world = np.linalg.inv(record["world_T_ref"][0].astype(np.float64))
    boxes, scores = [], []
    for v in range(rgb.shape[1]):
        cam1_T_cam0 = np.linalg.inv(w_cam[1, v]) @ w_cam[0, v]
        ref_T_cam0 = ref0_T_world @ w_cam[0, v]
        if variant == "oracle":
            flow = true_flow2d(record, v)
        else:
            flow = farneback_flow(rgb[0, v], rgb[1, v])
        found = moving_objects_from_flow2d(flow, depth[0, v], pix[v], threshold=threshold, min_pixels=min_pixels,
                                           stabilise=variant in ("stabilised", "oracle"), cam1_T_cam0=cam1_T_cam0,
                                           ref_T_cam0=ref_T_cam0)
        boxes += [d["box_ref"] for d in found]
        scores += [d["score"] for d in found]
    if not boxes:
        return np.zeros((0, 7)), np.zeros(0)
    boxes, scores = np.stack(boxes), np.asarray(scores, dtype=np.float64)
    keep = nms_bev(boxes, scores, 0.3)
    return boxes[keep], scores[keep]


def true_flow2d(record: dict, view: int) -> np.ndarray:
    """Ground-truth 2D flow of view `view` from step 0 to 1: H×W×2 pixels (0 where depth is missing).

    Like core.baselines.flow2d.oracle_flow2d, but the object motion is applied in `world` (gravity
    aligned, so the canonical boxes apply): the rig's cameras are pitched, and a box cannot be
    expressed in a pitched camera frame (boxes carry a yaw only)."""
    depth = torch.as_tensor(record["depth"][0, view], dtype=torch.float64)       # H×W
    H, W = depth.shape
    K = torch.as_tensor(record["pix_T_cam"][view], dtype=torch.float64)[None]  # 1×4×4
    w_cam = torch.as_tensor(record["world_T_cam"][:, view], dtype=torch.float64)  # T×4×4
    xyz0, valid = camera.depth_to_points(depth[None], K)                         # 1×N×3, 1×N
    xyz_w = se3.apply(w_cam[0:1], xyz0)[0]                                       # N×3 world
    both = torch.as_tensor(record["box_valid"][0] & record["box_valid"][1])
    b0 = torch.as_tensor(record["boxes"][0], dtype=torch.float64)[both][None]   # 1×K×7 world
    b1 = torch.as_tensor(record["boxes"][1], dtype=torch.float64)[both][None]
    moved = xyz_w.clone()
    if b0.shape[1]:
        inside = points_in_boxes(xyz_w[None], b0)[0]                             # N×K
        motion = se3.compose(box_T_obj(b1)[0], se3.invert(box_T_obj(b0)[0]))    # K×4×4 world
        owner = torch.where(inside.any(1), inside.float().argmax(1), -1)         # N
        for k in range(b0.shape[1]):
            sel = owner == k
            if sel.any():
                moved[sel] = se3.apply(motion[k:k + 1], xyz_w[sel][None])[0]
    uv0, _ = camera.project(K, xyz0)                                             # 1×N×2
    uv1, z1 = camera.project(K, se3.apply(se3.invert(w_cam[1:2]), moved[None]))  # 1×N×2, 1×N
    ok = valid[0] & (z1[0] > camera.MIN_DEPTH)
    flow = torch.where(ok[:, None], uv1[0] - uv0[0], torch.zeros_like(uv0[0]))   # N×2
    return flow.reshape(H, W, 2).numpy()                                         # H×W×2


@torch.no_grad()
def evaluate_moving(flow_bundles: dict, records: Iterable[dict], *, device, iou: float, grid,
                    flow2d_threshold: float, flow2d_min_pixels: int) -> dict:
    """flow_bundles: method-name prefix -> (bundle, stabilize modes), e.g.
    {"contrastive": (b, ("poses", "egomotion"))}. Returns per setting and method: AP, curve, counts."""
    accs: dict[str, dict[str, APAccumulator]] = {s: {} for s in SETTINGS}
    pairs = {s: 0 for s in SETTINGS}
    methods_2p5d = {"2.5D Farneback": "raw", "2.5D Farneback stabilised": "stabilised", "2.5D oracle flow": "oracle"}

    def add(setting: str, method: str, boxes, scores, gt) -> None:
        acc = accs[setting].setdefault(method, APAccumulator(iou_fn=iou_3d, thresholds=(iou,)))
        acc.add_frame(np.asarray(boxes, dtype=np.float64).reshape(-1, 7), np.asarray(scores, dtype=np.float64), gt)

    for record in records:
        if record["rgb"].shape[0] < 2:
            continue
        setting = "moving" if camera_moves(record) else "static"
        pairs[setting] += 1
        gt = moving_gt_ref0(record, grid)
        inputs = pair_inputs(record_batch(record, device), 0, 1)
        for prefix, (bundle, modes) in flow_bundles.items():
            for mode in modes:
                out = moving_objects(bundle, **inputs, stabilize=mode)
                valid = out["valid"][0]
                label = f"{prefix}, {'GT egomotion' if mode == 'poses' else 'egomotion module'}"
                add(setting, label, out["boxes"][0, valid].cpu().numpy(), out["scores"][0, valid].cpu().numpy(), gt)
        for method, variant in methods_2p5d.items():
            boxes, scores = baseline_2p5d(record, variant=variant, threshold=flow2d_threshold,
                                          min_pixels=flow2d_min_pixels)
            add(setting, method, boxes, scores, gt)

    result: dict = {"iou": iou, "pairs": pairs}
    for setting in SETTINGS:
        result[setting] = {}
        for method, acc in accs[setting].items():
            precision, recall, _ = acc.curve(iou)
            idx = np.unique(np.linspace(0, len(recall) - 1, min(CURVE_POINTS, len(recall))).astype(int)) if len(recall) else []
            result[setting][method] = {"ap": acc.ap(iou), "gt_boxes": acc.num_gt, "detections": acc.num_detections,
                                       "curve": {"precision": [float(precision[i]) for i in idx],
                                                 "recall": [float(recall[i]) for i in idx]}}
    return result

