"""Moving objects from egomotion-stabilised 3D flow: threshold, components, score, fit, NMS.

Inputs follow docs/conventions.md#3d-flow: flow 3×Z×Y×X in voxel units with channels (x, y, z), from frame t to
t+1, in the map grid of `ref` at t; occupancy Z×Y×X probabilities on the same grid. Boxes and
velocities come out in `ref` (metres, m/s).
"""

from __future__ import annotations

import numpy as np
import torch

from core.errors import ShapeError
from core.geometry.grid import GridConfig
from core.moving.boxfit import fit_box_to_voxels
from core.moving.components import component_indices, connected_components, to_numpy
from core.moving.nms import nms_bev
from core.moving.saliency import center_surround_score


def moving_objects_from_flow(flow, occupancy, grid: GridConfig, *, threshold: float, min_voxels: int,
                             dt: float, occupied_above: float = 0.5, shell_margin: float | None = None,
                             nms_iou: float = 0.3, connectivity: int = 26, can_move=None) -> list[dict]:
    """Scored oriented boxes of the independently moving objects.

    flow: 3×Z×Y×X voxels (x, y, z), stabilised (background ≈ 0). occupancy: Z×Y×X in [0, 1] or None
    (every voxel counts as occupied). threshold: flow magnitude (voxels) above which a voxel moves.
    min_voxels: smaller components are dropped. dt: seconds from t to t+1. occupied_above: occupancy
    threshold. shell_margin: metres of the saliency shell (default 2 voxels). nms_iou: BEV IoU above
    which a lower-scored box is suppressed. can_move: Z×Y×X bool or None — voxels outside it never count
    as moving (core.moving.ground.above_ground: nothing at or below the ground moves).

    Returns a list, best score first, of dicts: `box_ref` (7,) canonical box in ref, `score` (float,
    center-surround in [−1, 1]), `velocity_ref` (3,) mean velocity of the component's voxels in
    m/s along ref (x, y, z), `num_voxels` (int).
    """
    f = to_numpy(flow).astype(np.float64)
    if f.shape != (3, grid.Z, grid.Y, grid.X):
        raise ShapeError(f"flow: expected 3×{grid.Z}×{grid.Y}×{grid.X}, got {'×'.join(map(str, f.shape))}")
    if occupancy is None:
        occ = np.ones(f.shape[1:])
    else:
        occ = to_numpy(occupancy).astype(np.float64)
        if occ.shape != f.shape[1:]:
            raise ShapeError(f"occupancy: expected {grid.Z}×{grid.Y}×{grid.X}, got {'×'.join(map(str, occ.shape))}")
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")
    occupied = occ > occupied_above
    magnitude = np.linalg.norm(f, axis=0)                            # Z×Y×X voxels
    # Unoccupied voxels carry no motion (the paper zeroes their flow at test time).
    moving = (magnitude > threshold) & occupied
    if can_move is not None:
        allowed = to_numpy(can_move).astype(bool)
        if allowed.shape != moving.shape:
            raise ShapeError(f"can_move: expected {grid.Z}×{grid.Y}×{grid.X}, got {'×'.join(map(str, allowed.shape))}")
        moving &= allowed
    labels, count = connected_components(moving, connectivity=connectivity)
    margin = 2 * grid.voxel_size if shell_margin is None else shell_margin
    found = []
    for zyx in component_indices(labels, count):
        if len(zyx) < min_voxels:
            continue
        box = fit_box_to_voxels(zyx, grid)
        score = center_surround_score(moving, box, grid, weight=occupied, shell_margin=margin)
        mean_flow = f[:, zyx[:, 0], zyx[:, 1], zyx[:, 2]].mean(axis=1)  # 3 voxels, (x, y, z)
        found.append(dict(box_ref=box, score=score, velocity_ref=mean_flow * grid.voxel_size / dt,
                          num_voxels=int(len(zyx))))
    if not found:
        return []
    keep = nms_bev(np.stack([d["box_ref"] for d in found]), np.array([d["score"] for d in found]), nms_iou)
    return [found[i] for i in keep]


def detections_to_tensors(per_example: list[list[dict]], *, device=None,
                          dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Pack B lists of `moving_objects_from_flow` results into the padded tensors of
    core.pipeline.moving_objects: `boxes` B×K×7 (ref), `scores` B×K, `valid` B×K bool,
    `velocities` B×K×3 (m/s), with K the longest list (at least 1; padding rows are zero, not valid)."""
    B = len(per_example)
    K = max([1] + [len(d) for d in per_example])
    boxes = torch.zeros(B, K, 7, dtype=dtype)
    scores = torch.zeros(B, K, dtype=dtype)
    velocities = torch.zeros(B, K, 3, dtype=dtype)
    valid = torch.zeros(B, K, dtype=torch.bool)
    for b, dets in enumerate(per_example):
        for k, d in enumerate(dets):
            boxes[b, k] = torch.as_tensor(d["box_ref"], dtype=dtype)
            scores[b, k] = float(d["score"])
            velocities[b, k] = torch.as_tensor(d["velocity_ref"], dtype=dtype)
            valid[b, k] = True
    return {"boxes": boxes.to(device), "scores": scores.to(device), "valid": valid.to(device),
            "velocities": velocities.to(device)}
