"""Ground truth derived from a record: egomotion, occupancy, free space, 3D flow, moving-object mask.

Conventions (docs/conventions.md#frames): frames `pix`, `cam` (OpenCV), `ref` (the record's `world_T_ref[t]`,
gravity-aligned, anchored to the ego), `mem` (voxel indices, integer = voxel centre), `world`.
Poses are 4×4 `a_T_b` (p_a = a_T_b @ p_b). Volumes are C×Z×Y×X (one record, no batch dim); flow channels
are (x, y, z) in voxel units, pointing from step t to t+1. Boxes are the record's canonical world boxes.

A record is the dict of numpy arrays of docs/data.md#records; every function here reads it without changing it and
returns float32 torch tensors on the CPU. Poses are composed in float64 so large world offsets cost no
precision.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from core.geometry import boxes as gboxes
from core.geometry import camera, se3
from core.geometry.freespace import free_space
from core.geometry.grid import GridConfig, mem_T_ref, voxel_centers_ref
from core.geometry.poses import relative
from core.geometry.voxelize import points_to_voxel_index, voxelize

Record = Mapping[str, np.ndarray]

_VOXEL_CHUNK = 65536  # voxel centres tested against the boxes at once (bounds the N×K×3 temporaries)
# Depth points this close outside a box (metres) lie on its surface. The renderer puts an object's surface
# exactly on its box's faces, and float round-off leaves ~35 % of those points just outside them: on 8 small
# test records 31 663 points lie inside the exact boxes, 48 636 within 1 mm, 48 679 within 5 mm, 48 744 within
# 1 cm (the rest of that growth: ground points at the footprint's edge).
SURFACE_TOLERANCE_M = 0.005


def _f64(record: Record, key: str) -> torch.Tensor:
    return torch.as_tensor(np.asarray(record[key]), dtype=torch.float64)


def _check_step(record: Record, t: int, *, need_next: bool = False) -> int:
    T = int(record["world_T_ref"].shape[0])
    last = T - 2 if need_next else T - 1
    if not isinstance(t, (int, np.integer)) or not (0 <= t <= last):
        what = f"0 <= t <= T-2 = {last} (t and t+1 must exist)" if need_next else f"0 <= t <= T-1 = {last}"
        raise ValueError(f"step t={t!r} out of range: need {what}")
    return int(t)


def _views(record: Record, views: Sequence[int] | None) -> list[int]:
    V = int(record["world_T_cam"].shape[1])
    if views is None:
        return list(range(V))
    chosen = [int(v) for v in views]
    if not chosen or any(not (0 <= v < V) for v in chosen):
        raise ValueError(f"views={list(views)!r}: need a non-empty list of indices in [0, {V})")
    return chosen


# ----------------------------------------------------------------------------- egomotion

def gt_egomotion(record: Record, t0: int, t1: int) -> dict[str, torch.Tensor]:
    """Relative motion between steps t0 and t1.

    -> {"ref0_T_ref1": 4×4 (p_ref_t0 = ref0_T_ref1 @ p_ref_t1), "cam0_T_cam1": V×4×4 per view}, float32.
    """
    t0, t1 = _check_step(record, t0), _check_step(record, t1)
    world_T_ref = _f64(record, "world_T_ref")  # T×4×4
    world_T_cam = _f64(record, "world_T_cam")  # T×V×4×4
    return {
        "ref0_T_ref1": relative(world_T_ref[t0], world_T_ref[t1]).float(),
        "cam0_T_cam1": relative(world_T_cam[t0], world_T_cam[t1]).float(),
    }


# ----------------------------------------------------------------------------- points, occupancy, free space

def points_in_ref(record: Record, t: int, views: Sequence[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth points of the chosen views at step t in `ref` of step t.

    -> (xyz_ref: V'×(H·W)×3 float32, valid: V'×(H·W) bool), rows in the order of `views`.
    """
    t, views = _check_step(record, t), _views(record, views)
    depth = torch.as_tensor(np.asarray(record["depth"][t, views]), dtype=torch.float64)  # V'×H×W
    pix_T_cam = _f64(record, "pix_T_cam")[views]  # V'×4×4
    xyz_cam, valid = camera.depth_to_points(depth, pix_T_cam)  # V'×HW×3, V'×HW
    ref_T_cam = relative(_f64(record, "world_T_ref")[t], _f64(record, "world_T_cam")[t, views])  # V'×4×4
    return se3.apply(ref_T_cam, xyz_cam).float(), valid


def gt_occupancy(record: Record, t: int, grid: GridConfig, views: Sequence[int] | None = None) -> torch.Tensor:
    """Voxels holding at least one depth point of the chosen views (all by default), in `ref` of step t.

    -> 1×Z×Y×X float32 in {0, 1}.
    """
    xyz_ref, valid = points_in_ref(record, t, views)  # V'×N×3, V'×N
    return voxelize(xyz_ref.reshape(1, -1, 3), grid, valid.reshape(1, -1))[0]  # 1×Z×Y×X


def gt_free(record: Record, t: int, grid: GridConfig, views: Sequence[int] | None = None) -> torch.Tensor:
    """Voxels some camera ray of the chosen views crosses before reaching its depth point (ray traversal,
    `core.geometry.freespace.free_space`), minus the voxels that `gt_occupancy` marks occupied — a voxel
    seen occupied from one view is not free because another view's ray grazes it.

    -> 1×Z×Y×X float32 in {0, 1}, frame `ref` of step t.
    """
    t, views = _check_step(record, t), _views(record, views)
    depth = torch.as_tensor(np.asarray(record["depth"][t, views]), dtype=torch.float32)  # V'×H×W
    pix_T_cam = _f64(record, "pix_T_cam")[views].float()  # V'×4×4
    xyz_cam, valid = camera.depth_to_points(depth, pix_T_cam)  # V'×HW×3, V'×HW
    cam_T_ref = relative(_f64(record, "world_T_cam")[t, views], _f64(record, "world_T_ref")[t]).float()  # V'×4×4
    free = free_space(xyz_cam, valid, cam_T_ref, grid).amax(0)  # 1×Z×Y×X, union over views
    occupied = gt_occupancy(record, t, grid, views)
    return free * (1.0 - occupied)


# ----------------------------------------------------------------------------- flow and moving objects

def _first_box(points_world: torch.Tensor, boxes: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """points N×3 and boxes K×7 in world, `rows` K (each box's row in the record) -> N int64: the row of the
    first box holding each point (boxes do not overlap), -1 = none. In chunks of _VOXEL_CHUNK points."""
    owner = torch.full((points_world.shape[0],), -1, dtype=torch.long)
    if rows.numel() == 0:
        return owner
    for start in range(0, points_world.shape[0], _VOXEL_CHUNK):
        inside = gboxes.points_in_boxes(points_world[None, start:start + _VOXEL_CHUNK], boxes[None])[0]  # n×K
        first = inside.to(torch.int8).argmax(-1)  # n
        owner[start:start + _VOXEL_CHUNK] = torch.where(inside.any(-1), rows[first], -1)
    return owner


def _box_membership(record: Record, t: int, grid: GridConfig, rows: torch.Tensor) -> torch.Tensor:
    """Which box row (from `rows`, K' indices) holds each voxel centre at step t: Z·Y·X int64, -1 = none."""
    world_T_ref = _f64(record, "world_T_ref")[t]  # 4×4
    centres_world = se3.apply(world_T_ref, voxel_centers_ref(grid, dtype=torch.float64))  # ZYX×3
    return _first_box(centres_world, _f64(record, "boxes")[t, rows], rows)


def _surface_membership(record: Record, t: int, grid: GridConfig, rows: torch.Tensor) -> torch.Tensor:
    """Which box row (from `rows`) each voxel's depth points at step t (every view) all belong to: Z·Y·X
    int64, -1 = no point, a point of no box or of another box (a voxel holding the ground and a car's edge
    stays -1). A point belongs to a valid box when it lies inside it or within SURFACE_TOLERANCE_M of it."""
    n_vox = grid.Z * grid.Y * grid.X
    owner = torch.full((n_vox,), -1, dtype=torch.long)
    if rows.numel() == 0:
        return owner
    xyz_ref, valid = points_in_ref(record, t)  # V×N×3 float32 (as gt_occupancy voxelizes them), V×N
    xyz_ref = xyz_ref.reshape(1, -1, 3)[:, valid.reshape(-1)]  # 1×P×3
    flat, in_grid = points_to_voxel_index(xyz_ref, grid)  # 1×P, 1×P
    flat, xyz_ref = flat[0][in_grid[0]], xyz_ref[0][in_grid[0]]  # P', P'×3
    if flat.numel() == 0:
        return owner
    box_valid = torch.as_tensor(np.asarray(record["box_valid"][t]))
    every = box_valid.nonzero(as_tuple=True)[0]  # K_t: every valid box, moving or not
    boxes = _f64(record, "boxes")[t, every].clone()  # K_t×7
    boxes[:, 3:6] += 2.0 * SURFACE_TOLERANCE_M
    world = se3.apply(_f64(record, "world_T_ref")[t], xyz_ref.double())  # P'×3
    point_box = _first_box(world, boxes, every)  # P': a row of the record's boxes, -1 = none
    # A voxel is one box's when the smallest and the largest box row of its points agree (and are not -1).
    lowest = torch.full((n_vox,), n_vox, dtype=torch.long).scatter_reduce(0, flat, point_box, "amin")
    highest = torch.full((n_vox,), -2, dtype=torch.long).scatter_reduce(0, flat, point_box, "amax")
    one_box = (lowest == highest) & torch.isin(lowest, rows)  # ... and that box is one of `rows`
    owner[one_box] = lowest[one_box]
    return owner


def _object_membership(record: Record, t: int, grid: GridConfig, rows: torch.Tensor) -> torch.Tensor:
    """The box row (from `rows`) whose content each voxel holds at step t: its centre lies inside the box, or
    (centre in no box of `rows`) every depth point it holds lies on or in that box. Z·Y·X int64, -1 = none.
    Why both: an object's visible surface lies on its box's faces, so about half of the voxels holding it
    have their centre just outside the box — by centres alone they read as static background (16 small test
    records: 2 014 such voxels holding only moving objects' points, against 1 860 with centres inside)."""
    owner = _box_membership(record, t, grid, rows)
    surface = _surface_membership(record, t, grid, rows)
    return torch.where(owner >= 0, owner, surface)


def gt_flow(record: Record, t: int, grid: GridConfig, *, stabilised: bool = True) -> torch.Tensor:
    """Dense 3D scene flow from step t to t+1 at every voxel centre of the grid in `ref` of step t.

    A voxel holding box k's content at t (box valid at t and t+1; `_object_membership`: its centre inside the
    box, or every depth point in it on the box's surface) moves rigidly with the box:
    w' = box_k(t+1) ∘ box_k(t)^-1 · w (w = the voxel centre p in world); every other voxel is static
    background (w' = w).
    `stabilised=True`: displacement measured in `ref` of step t (static background -> 0; only objects
    that move in the world have flow). `stabilised=False`: the end point is expressed in `ref` of step t+1,
    so the background moves with the camera (the apparent motion a moving ego sees).

    -> 3×Z×Y×X float32, channels (x, y, z), voxel units (mem(end) − mem(start)).
    """
    t = _check_step(record, t, need_next=True)
    world_T_ref = _f64(record, "world_T_ref")  # T×4×4
    valid = torch.as_tensor(np.asarray(record["box_valid"]))
    rows = (valid[t] & valid[t + 1]).nonzero(as_tuple=True)[0]  # K'
    owner = _object_membership(record, t, grid, rows)  # ZYX

    centres_ref = voxel_centers_ref(grid, dtype=torch.float64)  # ZYX×3
    w = se3.apply(world_T_ref[t], centres_ref)  # ZYX×3
    boxes = _f64(record, "boxes")  # T×K×7
    K = boxes.shape[1]
    # world -> world motion of every box row over the step (identity for rows without a valid pair).
    motion = torch.eye(4, dtype=torch.float64).repeat(K + 1, 1, 1)  # (K+1)×4×4, last row = background
    if rows.numel() > 0:
        world_T_obj0 = gboxes.box_T_obj(boxes[t, rows])  # K'×4×4
        world_T_obj1 = gboxes.box_T_obj(boxes[t + 1, rows])
        motion[rows] = world_T_obj1 @ se3.invert(world_T_obj0)
    idx = torch.where(owner >= 0, owner, K)  # ZYX
    moved = (motion[idx, :3, :3] @ w.unsqueeze(-1)).squeeze(-1) + motion[idx, :3, 3]  # ZYX×3
    end_frame = t if stabilised else t + 1
    end_ref = se3.apply(se3.invert(world_T_ref[end_frame]), moved)  # ZYX×3
    mem_T = mem_T_ref(grid, dtype=torch.float64)
    flow = se3.apply(mem_T, end_ref) - se3.apply(mem_T, centres_ref)  # ZYX×3
    return flow.float().reshape(grid.Z, grid.Y, grid.X, 3).permute(3, 0, 1, 2).contiguous()  # 3×Z×Y×X


def gt_moving_mask(record: Record, t: int, grid: GridConfig) -> torch.Tensor:
    """Voxels (in `ref` of step t) holding the content of a valid box of an independently moving object
    (`box_moving`) at step t, by gt_flow's rule (`_object_membership`). -> 1×Z×Y×X float32 in {0, 1}."""
    t = _check_step(record, t)
    moving = torch.as_tensor(np.asarray(record["box_moving"])) & torch.as_tensor(np.asarray(record["box_valid"][t]))
    rows = moving.nonzero(as_tuple=True)[0]
    owner = _object_membership(record, t, grid, rows)  # ZYX
    return (owner >= 0).float().reshape(1, grid.Z, grid.Y, grid.X)
