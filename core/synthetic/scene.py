"""Scene sampling: ego trajectory, vehicles (the objects), static structures and their textures.

Everything is sampled in `ref0`, the ego's gravity-aligned frame at step 0 (X right, Y down, Z forward;
the ground is the plane y = +ground_y; the street runs along ref0 Z). Boxes are canonical
`(x, y, z, lx, ly, lz, yaw)` (centre, lengths along the object's x/y/z, yaw about Y, docs/conventions.md#boxes);
a vehicle's heading is its object +x axis, i.e. (cos yaw, 0, -sin yaw) in the frame.
Random draws come from one numpy Generator, so a seed fixes the scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from core.errors import N3dmapError
from core.geometry import boxes as gboxes
from core.geometry import se3
from core.geometry.grid import GridConfig
from core.synthetic import textures as tex
from core.synthetic.config import WorldConfig
from core.synthetic.raycast import ray_box_t

_SCENE_ATTEMPTS = 25      # whole-scene retries until some vehicle is inside the grid at every step
_PLACE_ATTEMPTS = 30      # retries per vehicle / structure placement


@dataclass
class Scene:
    """A sampled world (all float64 CPU tensors, frame `ref0` unless named otherwise).

    ref0_T_ref: T×4×4 ego reference frame at each step; world_T_ref0: 4×4;
    vehicles: T×n×7 boxes; vehicle_moving: n bool; structures: m×7 static boxes;
    textures: (n+m)×N_TEX texture rows (vehicles first); ref_T_cam: V×4×4 rig.
    """

    ref0_T_ref: torch.Tensor
    world_T_ref0: torch.Tensor
    vehicles: torch.Tensor
    vehicle_moving: np.ndarray
    structures: torch.Tensor
    textures: torch.Tensor
    ref_T_cam: torch.Tensor


# ----------------------------------------------------------------------------- ego and world

def sample_ego(rng: np.random.Generator, T: int, cfg: WorldConfig, moving: bool) -> torch.Tensor:
    """ref0_T_ref: T×4×4 float64. A moving ego drives forward (+Z) and turns at a constant yaw rate."""
    speed = rng.uniform(*cfg.ego_speed) if moving else 0.0
    yaw_rate = rng.uniform(-cfg.ego_yaw_rate, cfg.ego_yaw_rate) if moving else 0.0
    yaw = np.zeros(T)
    pos = np.zeros((T, 3))
    for t in range(1, T):
        mid = yaw[t - 1] + 0.5 * yaw_rate * cfg.dt
        pos[t] = pos[t - 1] + speed * cfg.dt * np.array([math.sin(mid), 0.0, math.cos(mid)])  # ref +Z is forward
        yaw[t] = yaw[t - 1] + yaw_rate * cfg.dt
    return se3.from_rt(se3.yaw_to_matrix(torch.from_numpy(yaw)), torch.from_numpy(pos))


def sample_world_T_ref0(rng: np.random.Generator, cfg: WorldConfig) -> torch.Tensor:
    """A random yaw and horizontal shift (gravity stays along +Y, so the ground keeps its height)."""
    yaw = torch.tensor(rng.uniform(-math.pi, math.pi), dtype=torch.float64)
    shift = torch.tensor([rng.uniform(-1, 1) * cfg.world_offset, 0.0, rng.uniform(-1, 1) * cfg.world_offset],
                         dtype=torch.float64)
    return se3.from_rt(se3.yaw_to_matrix(yaw), shift)


# ----------------------------------------------------------------------------- overlap helpers

def _bev_overlap(a: np.ndarray, b: np.ndarray, margin: float) -> np.ndarray:
    """Do boxes (rows x,y,z,lx,ly,lz,yaw) overlap in bird's-eye view (x, z), each grown by `margin`?
    Separating-axis test on the two rectangles. a, b: ...×7 (broadcast) -> ... bool."""
    def axes(box):  # ...×2×2: rows are the object's x and z axes in (x, z)
        c, s = np.cos(box[..., 6]), np.sin(box[..., 6])
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    a, b = np.broadcast_arrays(a, b)
    ha = a[..., [3, 5]] * 0.5 + margin  # ...×2
    hb = b[..., [3, 5]] * 0.5 + margin
    Aa, Ab = axes(a), axes(b)
    d = b[..., [0, 2]] - a[..., [0, 2]]  # ...×2
    separated = np.zeros(a.shape[:-1], bool)
    for axis in (Aa[..., 0, :], Aa[..., 1, :], Ab[..., 0, :], Ab[..., 1, :]):  # ...×2 each
        ra = (np.abs(np.einsum("...ij,...j->...i", Aa, axis)) * ha).sum(-1)
        rb = (np.abs(np.einsum("...ij,...j->...i", Ab, axis)) * hb).sum(-1)
        separated |= np.abs((d * axis).sum(-1)) > ra + rb
    return ~separated


def _overlaps_any(track: np.ndarray, others: np.ndarray, margin: float) -> bool:
    """track: T×7 (or 1×7 static), others: M×T×7 (or M×1×7) -> any BEV overlap at any step."""
    if len(others) == 0:
        return False
    return bool(_bev_overlap(track[None], others, margin).any())


def _blocks_views(boxes: np.ndarray, cam_centres: torch.Tensor, targets: torch.Tensor, clearance: float) -> np.ndarray:
    """Which static boxes (M×7) come within `clearance` of a camera centre, or cut the segment from a
    camera to its target? cam_centres, targets: N×3 in the boxes' frame -> M bool."""
    grown = torch.from_numpy(boxes.copy())
    grown[:, 3:6] += 2.0 * clearance
    obj_T_frame = se3.invert(gboxes.box_T_obj(grown))  # M×4×4
    M, N = grown.shape[0], cam_centres.shape[0]
    o = se3.apply(obj_T_frame, cam_centres.expand(M, N, 3))  # M×N×3
    half = 0.5 * grown[:, None, 3:6].expand(M, N, 3)
    inside = (o.abs() < half).all(-1).any(-1)  # M
    d = se3.apply(obj_T_frame, targets.expand(M, N, 3)) - o  # M×N×3, segment as a ray with t in [0, 1]
    cut = (ray_box_t(o, d, half, near=0.0) <= 1.0).any(-1)  # M
    return (inside | cut).numpy()


# ----------------------------------------------------------------------------- vehicles

def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _texture_row(rng: np.random.Generator, cfg: WorldConfig, colour_a: np.ndarray, kind: int | None = None) -> np.ndarray:
    row = np.zeros(tex.N_TEX)
    row[tex.KIND] = rng.integers(0, 3) if kind is None else kind
    row[tex.SCALE] = rng.uniform(*cfg.texture_scale)
    row[tex.SEED] = rng.uniform(0.0, tex.LATTICE)  # offset into the noise lattice
    row[tex.AXIS] = rng.integers(0, 2)
    row[tex.COLOUR_A] = colour_a
    # Second colour: darker/lighter shade or a contrasting hue, so patterns are visible.
    if rng.random() < 0.5:
        row[tex.COLOUR_B] = np.clip(colour_a * rng.uniform(0.3, 0.6), 0, 1)
    else:
        row[tex.COLOUR_B] = _hsv_to_rgb(rng.random(), rng.uniform(0.2, 0.8), rng.uniform(0.4, 0.95))
    return row


def _vehicle_track(rng: np.random.Generator, T: int, cfg: WorldConfig, ground_y: float,
                   anchor_z: float, moving: bool) -> np.ndarray:
    """One vehicle's boxes over time: T×7 in ref0."""
    lx, ly, lz = (rng.uniform(*cfg.vehicle_length), rng.uniform(*cfg.vehicle_height), rng.uniform(*cfg.vehicle_width))
    A = cfg.vehicle_area
    if moving:
        if rng.random() < 0.7:  # along the street, right-hand traffic: +Z lane at x > 0
            direction = 1.0 if rng.random() < 0.5 else -1.0
            x = direction * cfg.road_half_width * 0.5 + rng.uniform(-0.3, 0.3)
            yaw = -direction * math.pi / 2 + rng.uniform(-0.15, 0.15)
        else:  # crossing traffic
            x = rng.uniform(-A, A)
            yaw = (0.0 if rng.random() < 0.5 else math.pi) + rng.uniform(-0.15, 0.15)
        speed = rng.uniform(*cfg.vehicle_speed)
        yaw_rate = rng.uniform(-cfg.vehicle_yaw_rate, cfg.vehicle_yaw_rate)
    else:
        if rng.random() < 0.5:  # parked at the kerb
            side = 1.0 if rng.random() < 0.5 else -1.0
            x = side * (cfg.road_half_width - 0.5 * lz - 0.3)
            yaw = (math.pi / 2 if rng.random() < 0.5 else -math.pi / 2) + rng.uniform(-0.05, 0.05)
        else:  # parked anywhere in the open
            x = rng.uniform(-A, A)
            yaw = rng.uniform(-math.pi, math.pi)
        speed, yaw_rate = 0.0, 0.0
    z = anchor_z + rng.uniform(-A, A)
    track = np.zeros((T, 7))
    track[:, 3:6] = (lx, ly, lz)
    track[:, 1] = ground_y - 0.5 * ly
    track[0, [0, 2, 6]] = (x, z, yaw)
    for t in range(1, T):
        mid = track[t - 1, 6] + 0.5 * yaw_rate * cfg.dt
        track[t, 0] = track[t - 1, 0] + speed * cfg.dt * math.cos(mid)
        track[t, 2] = track[t - 1, 2] - speed * cfg.dt * math.sin(mid)
        track[t, 6] = track[t - 1, 6] + yaw_rate * cfg.dt
    return track


def boxes_inside_grid(boxes_ref0: torch.Tensor, ref0_T_ref: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """Which boxes lie entirely inside the grid bounds of `ref` at each step.

    boxes_ref0: T×n×7 (ref0), ref0_T_ref: T×4×4 -> T×n bool.
    """
    T, n = boxes_ref0.shape[:2]
    corners = gboxes.box_corners(boxes_ref0)  # T×n×8×3
    ref_T_ref0 = se3.invert(ref0_T_ref)  # T×4×4
    c_ref = se3.apply(ref_T_ref0, corners.reshape(T, n * 8, 3)).reshape(T, n, 8, 3)  # T×n×8×3
    lo = torch.tensor(grid.bounds_min, dtype=c_ref.dtype)
    hi = torch.tensor(grid.bounds_max, dtype=c_ref.dtype)
    return ((c_ref >= lo) & (c_ref <= hi)).all(-1).all(-1)


# ----------------------------------------------------------------------------- structures

def _structure_candidate(rng: np.random.Generator, kind: str, cfg: WorldConfig, ground_y: float,
                         anchor_z: float) -> np.ndarray:
    side = 1.0 if rng.random() < 0.5 else -1.0
    kerb = cfg.road_half_width + cfg.sidewalk_width
    z = anchor_z + rng.uniform(-25.0, 25.0)
    if kind == "building":
        lx, lz, ly = rng.uniform(5, 14), rng.uniform(5, 14), rng.uniform(4, 14)
        x = side * (kerb + 0.5 * lx + rng.uniform(0.0, 4.0))
        yaw = rng.uniform(-0.1, 0.1)
    elif kind == "wall":
        lx, lz, ly = rng.uniform(3, 10), 0.3, rng.uniform(0.8, 2.0)
        x = side * (kerb - 0.3)
        yaw = math.pi / 2 + rng.uniform(-0.05, 0.05)
    else:  # pole
        lx = lz = rng.uniform(0.2, 0.4)
        ly = rng.uniform(3.0, 6.0)
        x = side * (cfg.road_half_width + rng.uniform(0.4, cfg.sidewalk_width - 0.3))
        yaw = rng.uniform(-math.pi, math.pi)
    return np.array([x, ground_y - 0.5 * ly, z, lx, ly, lz, yaw])


_STRUCTURE_COLOURS = {
    "building": [(0.62, 0.36, 0.28), (0.72, 0.7, 0.64), (0.55, 0.57, 0.62), (0.82, 0.76, 0.58), (0.4, 0.42, 0.45)],
    "wall": [(0.6, 0.6, 0.58), (0.5, 0.32, 0.25)],
    "pole": [(0.35, 0.36, 0.38), (0.2, 0.3, 0.22)],
}


# ----------------------------------------------------------------------------- the scene

def sample_scene(rng: np.random.Generator, *, T: int, V: int, cfg: WorldConfig, grid: GridConfig,
                 ground_y: float, moving_ego: bool) -> Scene:
    """Sample a scene where at least one vehicle lies inside the grid (in `ref` of that step) at every
    step. Raises N3dmapError when the config makes that impossible in a few attempts."""
    from core.synthetic.rig import sample_rig  # local import: rig is a sibling leaf module

    for _ in range(_SCENE_ATTEMPTS):
        ref0_T_ref = sample_ego(rng, T, cfg, moving_ego)
        world_T_ref0 = sample_world_T_ref0(rng, cfg)
        centre = tuple(0.5 * (a + b) for a, b in zip(grid.bounds_min, grid.bounds_max))
        ref_T_cam = sample_rig(rng, V, cfg, centre)
        anchor_z = float(ref0_T_ref[T // 2, 2, 3])  # place things around the ego's mid-trajectory

        n_target = min(int(rng.integers(cfg.num_vehicles[0], cfg.num_vehicles[1] + 1)), cfg.max_objects)
        tracks = np.zeros((0, T, 7))
        moving: list[bool] = []
        for _ in range(n_target):
            is_moving = bool(rng.random() < cfg.moving_fraction)
            for _ in range(_PLACE_ATTEMPTS):
                track = _vehicle_track(rng, T, cfg, ground_y, anchor_z, is_moving)
                if not _overlaps_any(track, tracks, margin=0.5):
                    tracks = np.concatenate([tracks, track[None]])
                    moving.append(is_moving)
                    break
        if len(tracks) == 0:
            continue
        vehicles = torch.from_numpy(tracks).transpose(0, 1).contiguous()  # T×n×7
        inside = boxes_inside_grid(vehicles, ref0_T_ref, grid)  # T×n
        if not bool(inside.any(-1).all()):
            continue

        # Cameras (at every step) and their look-at targets, in ref0, for structure rejection.
        ref0_T_cam = (ref0_T_ref[:, None] @ ref_T_cam[None]).reshape(T * V, 4, 4)  # T·V×4×4
        cam_centres = ref0_T_cam[:, :3, 3]
        target_ref = torch.tensor(centre, dtype=torch.float64).expand(T, 3).unsqueeze(1)  # T×1×3
        targets = se3.apply(ref0_T_ref, target_ref)[:, 0]  # T×3
        targets = targets.repeat_interleave(V, dim=0)  # T·V×3
        # Draw a few candidates per wanted structure, reject those in a camera's way at once, then keep
        # the first non-overlapping ones of each kind.
        wanted, kinds, cands = [], [], []
        for kind, count in (("building", cfg.num_buildings), ("wall", cfg.num_walls), ("pole", cfg.num_poles)):
            n_kind = int(rng.integers(count[0], count[1] + 1))
            wanted.append(n_kind)
            for _ in range(n_kind * (_PLACE_ATTEMPTS // 3)):
                kinds.append(kind)
                cands.append(_structure_candidate(rng, kind, cfg, ground_y, anchor_z))
        structures: list[np.ndarray] = []
        rows: list[np.ndarray] = []
        if cands:
            cands_arr = np.stack(cands)
            blocked = _blocks_views(cands_arr, cam_centres, targets, cfg.camera_clearance)
            placed = {"building": 0, "wall": 0, "pole": 0}
            quota = dict(zip(("building", "wall", "pole"), wanted))
            for kind, cand, bad in zip(kinds, cands_arr, blocked):
                if bad or placed[kind] >= quota[kind]:
                    continue
                if _overlaps_any(cand[None], tracks, margin=0.3) or (
                        structures and _overlaps_any(cand[None], np.stack(structures)[:, None], margin=0.3)):
                    continue
                structures.append(cand)
                placed[kind] += 1
                palette = _STRUCTURE_COLOURS[kind]
                base = np.array(palette[int(rng.integers(len(palette)))]) * rng.uniform(0.85, 1.15)
                rows.append(_texture_row(rng, cfg, np.clip(base, 0, 1)))
        vehicle_rows = [_texture_row(rng, cfg, _hsv_to_rgb(rng.random(), rng.uniform(0.5, 0.95), rng.uniform(0.45, 0.95)))
                        for _ in tracks]
        return Scene(
            ref0_T_ref=ref0_T_ref, world_T_ref0=world_T_ref0, vehicles=vehicles,
            vehicle_moving=np.array(moving, dtype=bool),
            structures=torch.from_numpy(np.stack(structures)) if structures else torch.zeros(0, 7, dtype=torch.float64),
            textures=torch.from_numpy(np.stack(vehicle_rows + rows)),
            ref_T_cam=ref_T_cam,
        )
    raise N3dmapError(f"synthetic world: could not place a vehicle inside the grid at all {T} steps in "
                      f"{_SCENE_ATTEMPTS} attempts (grid {grid.bounds_min}..{grid.bounds_max}; try fewer frames "
                      "or a slower ego/vehicles)")
