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
from core.moving.amodal import SizePrior, amodal_box, split_oversized
from core.moving.boxfit import fit_box_to_points, fit_box_to_voxels, voxel_indices_to_ref
from core.moving.components import component_indices, connected_components, to_numpy
from core.moving.ground import ground_y_at
from core.moving.nms import nms_bev
from core.moving.saliency import center_surround_score

# What a voxel marked moving means, and so how far a box of voxel centres is padded (in voxels):
# "surface" — a surface of the object passes through the voxel (flow predicted over the voxels that hold
# depth points spreads to all of them, whether their centres lie in the object or just outside it); the
# centres scatter about the surface by ± half a voxel, so the centres' box is the object's (pad 0).
# "centres" — the voxel's centre lies inside the object (a flow that moves only those: the true flow of
# core.data.ground_truth.gt_flow until session 24, which now also moves the voxels holding only an object's
# surface points, as a model's flow does); the centres then span about a voxel less than the object (pad one voxel).
# Measured (n3dmap eval moving, small preset, a 300-step trained chain, development sets of 16 and 32
# records): the model's boxes at AP3D@0.5 static / moving camera 0.112 / 0.088 with pad one voxel, 0.370 /
# 0.343 with pad 0 (32 records: 0.111 / 0.079 → 0.354 / 0.346); the true flow's 0.306 / 0.569 with one voxel
# and 0.373 / 0.519 with 0 (32 records: 0.425 / 0.180 → 0.216 / 0.129; both with the saliency box unpadded
# too, in a first version).
MOVING_VOXEL_PAD = {"surface": 0.0, "centres": 1.0}
# A component's bird's-eye flow is coherent, and gives the amodal box its heading (core.moving.amodal,
# rule 3), when the length of its voxels' mean flow is at least this share of their mean flow length
# (1: all parallel). Measured on 32 small-preset development pairs: the true flow's components are all
# coherent, its direction within 20° of the object's heading for every one, while their visible boxes'
# long axes are for 78 % (70 % of the one-voxel-thin strips); a 300-step model's flow is within 20° for
# 90 % of its components at coherence ≥ 0.95 and 44–63 % below 0.9, where its visible boxes' long axes
# (84–93 %) are the better guide.
HEADING_COHERENCE = 0.95
# Hysteresis of the motion threshold: voxels above this share of it join a moving component when the
# component holds a voxel above the threshold itself. Why: a model's flow is smooth and underestimates
# motion, so above the threshold alone a car falls apart into fragments (partial boxes, and an
# unlabelled size prior estimated from fragments: 2.0 × 0.5 m). Measured (n3dmap eval moving, small
# preset, 300-step chain, 32 held-out development records, fixed size prior 4.3 × 1.9 × 1.65 m),
# AP3D@0.5 static / moving camera: stabilised with the true poses 0.178 / 0.113 → 0.234 / 0.154 at 0.5;
# with the bundle's egomotion 0.399 / 0.329 → 0.583 / 0.492 (0.25: 0.624 / 0.494 with the estimated prior).
DEFAULT_HYSTERESIS = 0.5


def moving_objects_from_flow(flow, occupancy, grid: GridConfig, *, threshold: float, min_voxels: int,
                             dt: float, occupied_above: float = 0.5, shell_margin: float | None = None,
                             nms_iou: float = 0.3, connectivity: int = 26, can_move=None,
                             size_prior: SizePrior | None = None, viewpoints=None, ground=None,
                             moving_voxels: str = "surface", seen_by=None,
                             hysteresis: float = DEFAULT_HYSTERESIS, object_threshold: float = 0.0) -> list[dict]:
    """Scored oriented boxes of the independently moving objects.

    flow: 3×Z×Y×X voxels (x, y, z), stabilised (background ≈ 0). occupancy: Z×Y×X in [0, 1] or None
    (every voxel counts as occupied). threshold: flow magnitude (voxels) above which a voxel moves.
    min_voxels: smaller components are dropped. dt: seconds from t to t+1. occupied_above: occupancy
    threshold. shell_margin: metres of the saliency shell (default 2 voxels). nms_iou: BEV IoU above
    which a lower-scored box is suppressed. can_move: Z×Y×X bool or None — voxels outside it never count
    as moving (core.moving.ground.above_ground: nothing at or below the ground moves). size_prior: None —
    each component's box covers its voxels (the visible part); a SizePrior — amodal boxes
    (core.moving.amodal): oversized components are split or dropped, and each box grows to a whole object
    away from the cameras that saw it (`seen_by`; without it the nearest of `viewpoints`, V×3 camera
    centres in ref, metres; None: symmetrically), along its coherent flow's heading (HEADING_COHERENCE),
    and down to the `ground` plane (4,) (core.moving.ground; None: the visible vertical extent).
    moving_voxels: "surface" or "centres", what a moving voxel means (MOVING_VOXEL_PAD): the boxes of
    voxel centres are padded by 0 or by one voxel (and are at least one voxel thick).
    hysteresis: in (0, 1]; voxels above hysteresis × threshold count when connected to one above the
    threshold (moving_mask; 1: the threshold alone). object_threshold: a component (or piece of one) whose
    mean flow (voxels) is slower is no moving object. seen_by: V×Z×Y×X bool or None — which of the
    `viewpoints` saw each voxel (held one of its depth points); an amodal box then grows away from the
    cameras that saw its component (their centres averaged, weighted by how many of its voxels each saw),
    not from the nearest camera, which on a rig around the scene is often one that saw other faces or none.

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
    check_options(moving_voxels=moving_voxels, hysteresis=hysteresis)
    pad = MOVING_VOXEL_PAD[moving_voxels] * grid.voxel_size
    occupied = occ > occupied_above
    magnitude = np.linalg.norm(f, axis=0)                            # Z×Y×X voxels
    # Unoccupied voxels carry no motion (the paper zeroes their flow at test time).
    candidates = occupied
    if can_move is not None:
        allowed = to_numpy(can_move).astype(bool)
        if allowed.shape != occupied.shape:
            raise ShapeError(f"can_move: expected {grid.Z}×{grid.Y}×{grid.X}, got {'×'.join(map(str, allowed.shape))}")
        candidates = occupied & allowed
    moving = moving_mask(magnitude, candidates, threshold=threshold, hysteresis=hysteresis,
                         connectivity=connectivity)
    labels, count = connected_components(moving, connectivity=connectivity)
    margin = 2 * grid.voxel_size if shell_margin is None else shell_margin
    found = []
    views = None if viewpoints is None else to_numpy(viewpoints).astype(np.float64).reshape(-1, 3)
    seen = None
    if seen_by is not None:
        seen = to_numpy(seen_by).astype(bool)
        if views is None or seen.shape != (len(views),) + f.shape[1:]:
            raise ShapeError(f"seen_by: expected V×{grid.Z}×{grid.Y}×{grid.X} with V the viewpoints' count "
                             f"({None if views is None else len(views)}), got {'×'.join(map(str, seen.shape))}")
    for component in component_indices(labels, count):
        if len(component) < min_voxels:
            continue
        pieces = [component] if size_prior is None else _pieces(component, grid, size_prior, pad)
        for zyx in pieces:
            if len(zyx) < min_voxels:
                continue
            voxel_flow = f[:, zyx[:, 0], zyx[:, 1], zyx[:, 2]]  # 3×N voxels, (x, y, z)
            mean_flow = voxel_flow.mean(axis=1)                # 3
            if np.linalg.norm(mean_flow) < object_threshold:   # the piece as a whole barely moves
                continue
            # Saliency scores the voxels seen to move (the box covering them whole), not the hidden part of
            # the object.
            score_box = fit_box_to_voxels(zyx, grid)  # 7
            score = center_surround_score(moving, score_box, grid, weight=occupied, shell_margin=margin)
            box = fit_box_to_points(voxel_indices_to_ref(zyx, grid), pad=pad, min_extent=grid.voxel_size) \
                if size_prior is None else amodal_box(
                voxel_indices_to_ref(zyx, grid), viewpoint=_viewpoint(views, seen, zyx, grid), prior=size_prior,
                voxel=grid.voxel_size, pad=pad, heading=coherent_heading(voxel_flow),
                ground_y=None if ground is None else ground_y_at(ground, score_box[0], score_box[2]))
            found.append(dict(box_ref=box, score=score, velocity_ref=mean_flow * grid.voxel_size / dt,
                              num_voxels=int(len(zyx))))
    if not found:
        return []
    keep = nms_bev(np.stack([d["box_ref"] for d in found]), np.array([d["score"] for d in found]), nms_iou)
    return [found[i] for i in keep]


def check_options(*, moving_voxels: str, hysteresis: float) -> None:
    """ValueError naming the option when `moving_voxels` is not a MOVING_VOXEL_PAD key or `hysteresis` is
    outside (0, 1] (moving_objects_from_flow and core.pipeline.moving_boxes.MovingObjectsConfig)."""
    if moving_voxels not in MOVING_VOXEL_PAD:
        raise ValueError(f"moving_voxels must be one of {sorted(MOVING_VOXEL_PAD)}, got {moving_voxels!r}")
    if not 0 < hysteresis <= 1:
        raise ValueError(f"hysteresis must be in (0, 1], got {hysteresis}")


def moving_mask(magnitude: np.ndarray, candidates: np.ndarray, *, threshold: float, hysteresis: float,
                connectivity: int = 26) -> np.ndarray:
    """magnitude Z×Y×X (voxels), candidates Z×Y×X bool (voxels that may move) -> Z×Y×X bool: hysteresis
    as Canny's edges — the components of candidates above `hysteresis` × threshold that hold at least one
    voxel above the threshold itself (DEFAULT_HYSTERESIS); hysteresis 1: above the threshold alone."""
    weak = (magnitude > hysteresis * threshold) & candidates
    if hysteresis >= 1:
        return weak
    labels, _ = connected_components(weak, connectivity=connectivity)
    seeded = np.unique(labels[weak & (magnitude > threshold)])                 # component ids with a seed
    return weak & np.isin(labels, seeded[seeded > 0])


def coherent_heading(voxel_flow: np.ndarray) -> np.ndarray | None:
    """voxel_flow: 3×N flows (x, y, z) of one component -> its bird's-eye direction (2,) in (x, z) when the
    voxels move as one (HEADING_COHERENCE), else None."""
    bev = voxel_flow[[0, 2]]                                  # 2×N
    mean = bev.mean(axis=1)                                   # 2
    spread = float(np.linalg.norm(bev, axis=0).mean())
    if spread == 0 or np.linalg.norm(mean) < HEADING_COHERENCE * spread:
        return None
    return mean / np.linalg.norm(mean)


def _pieces(zyx: np.ndarray, grid: GridConfig, prior: SizePrior, pad: float) -> list[np.ndarray]:
    """The component's voxels N×3 (z, y, x) split into object-sized pieces (core.moving.amodal; pad metres)."""
    pieces, _ = split_oversized(voxel_indices_to_ref(zyx, grid), prior, voxel=grid.voxel_size, pad=pad)
    return [zyx[index] for index in pieces]


def _viewpoint(views: np.ndarray | None, seen: np.ndarray | None, zyx: np.ndarray,
               grid: GridConfig) -> np.ndarray | None:
    """Where the component with voxels N×3 (z, y, x) was seen from (3,): the centres of the cameras that
    saw its voxels, weighted by how many each saw (seen: V×Z×Y×X); without that record, or when no camera
    saw them, the camera nearest to the voxels' centroid; None without cameras."""
    if views is None or len(views) == 0:
        return None
    if seen is not None:
        counts = seen[:, zyx[:, 0], zyx[:, 1], zyx[:, 2]].sum(axis=1).astype(np.float64)  # V
        if counts.sum() > 0:
            return counts @ views / counts.sum()
    centroid = voxel_indices_to_ref(zyx, grid).mean(0)
    return views[int(np.argmin(((views - centroid) ** 2).sum(1)))]


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
