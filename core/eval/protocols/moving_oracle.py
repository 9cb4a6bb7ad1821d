"""The oracle row of the moving-object evaluation: the true stabilised 3D flow and the true occupancy
through the 3D method's own post-processing — an upper bound of that post-processing.

Frames (docs/conventions.md#frames): everything is in ref_t of the pair (t, t+1); flow in voxels.
"""

from __future__ import annotations

import numpy as np
import torch

from core.data.ground_truth import gt_flow, points_in_ref
from core.geometry.poses import camera_centres, rig_cam_T_ref
from core.geometry.voxelize import voxelize
from core.moving.ground import fit_ground_plane
from core.pipeline.moving import MovingObjectsConfig, boxes_from_flow


def pair_ground(record, t: int, config: MovingObjectsConfig) -> np.ndarray | None:
    """The ground plane (4,) of pair (t, t+1) in ref_t, fitted to frame t's depth points as the 3D methods fit
    theirs; None when `config` has no ground gate (`ground_margin` None). The 2.5D baselines stand their
    boxes on it and drop the pixels at or below it: in the scored pairs and when their size prior is
    estimated alike (core.eval.protocols.moving.baseline_priors)."""
    xyz, valid = points_in_ref(record, t)                                       # V×H×W×3, V×H×W
    return _ground_of(xyz, valid, config)


def _ground_of(xyz: torch.Tensor, valid: torch.Tensor, config: MovingObjectsConfig) -> np.ndarray | None:
    return fit_ground_plane(xyz[valid].double().numpy()) if config.ground_margin is not None else None


def oracle_boxes(record, t: int, grid, config: MovingObjectsConfig) -> dict:
    """The true stabilised flow and occupancy of pair (t, t+1) through the post-processing of `config`
    (a batch of one): core.pipeline.moving.boxes_from_flow's dict plus `flow` 1×3×Z×Y×X, `observed`
    1×1×Z×Y×X and `ground`, the frame's ground plane (4,) or None (the 2.5D baselines stand their boxes on it). The true flow moves the voxels that hold an object's content (core.data.ground_truth: its
    centre inside the object, or only the object's surface points in it), as a model's flow does, so its
    boxes are made as the model's are (`config.moving_voxels`, "surface" by default: unpadded). Measured on
    the small report's 64 test records (session 24), AP3D@0.5 static / moving camera: 1.000 / 1.000 this way;
    0.616 / 0.741 when the true flow moved only the voxels with centres inside (half of the voxels holding
    the visible surface read as static) and its boxes were padded one voxel."""
    true_flow = gt_flow(record, t, grid)[None]                                  # 1×3×Z×Y×X
    xyz, valid = points_in_ref(record, t)                                       # V×H×W×3, V×H×W
    ground = [_ground_of(xyz, valid, config)]                                   # the same ground plane rule
    cam_T_ref = rig_cam_T_ref(torch.as_tensor(record["world_T_cam"][t], dtype=torch.float64)[None],
                              torch.as_tensor(record["world_T_ref"][t], dtype=torch.float64)[None])  # 1×V×4×4
    viewpoints = camera_centres(cam_T_ref).float()                              # 1×V×3 camera centres in ref
    seen_by = (voxelize(xyz, grid, valid)[:, 0] > 0)[None]                     # 1×V×Z×Y×X, each view's points
    observed = seen_by.any(dim=1, keepdim=True).float()                        # 1×1×Z×Y×X (gt_occupancy)
    out = boxes_from_flow(true_flow, observed, grid, config, ground=ground,
                          viewpoints=viewpoints, seen_by=seen_by)
    return {**out, "flow": true_flow, "observed": observed, "ground": ground[0]}
