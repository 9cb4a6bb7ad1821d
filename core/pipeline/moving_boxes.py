"""From stabilised 3D flow to moving-object boxes: the post-processing of core.pipeline.moving.

Per example keep the voxels that frame 0's depth points occupy (`occupancy="observed"`, the default;
the occupancy head alone fills in unseen space where flow is noise) and that lie above the ground plane
fitted to those points, threshold the flow magnitude, take 3D connected components, score each by
center-surround motion saliency, fit an oriented box, and suppress overlaps
(core.moving.detect_moving.moving_objects_from_flow). Both gates were measured to matter: on tiny
held-out pairs the boxes from briefly trained flow went from AP3D@0.25 ≈ 0 to ≈ 0.46 with them.

Frames (docs/conventions.md#frames): everything here is in `ref0`. Boxes are canonical (x, y, z, lx, ly,
lz, yaw); velocities are m/s along ref0's axes. Flow is B×3×Z×Y×X in voxels, channels (x, y, z), t0 -> t1.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import torch

from core.geometry import se3
from core.geometry.camera import depth_to_points
from core.geometry.grid import GridConfig
from core.geometry.poses import camera_centres
from core.geometry.voxelize import voxelize
from core.moving.amodal import SizePrior
from core.moving.detect_moving import (DEFAULT_HYSTERESIS, check_options, detections_to_tensors,
                                       moving_objects_from_flow)
from core.moving.ground import DEFAULT_MARGIN_VOXELS, above_ground, fit_ground_plane

BOXES_FRAME = "ref0"
# Seconds between the two frames when the caller gives no interval: the built-in synthetic world's step
# (core.synthetic.config.WorldConfig.dt). Only the velocities' scale and the speed threshold use it.
DEFAULT_DT = 0.2
OCCUPANCY_SOURCES = ("observed", "predicted")


@dataclass(frozen=True)
class MovingObjectsConfig:
    """Post-processing of the stabilised flow into boxes (see moving_objects_from_flow)."""

    dt: float = DEFAULT_DT          # seconds from t0 to t1
    # m/s: voxels whose flow is slower do not move (with `hysteresis`). Why 0.25 (it was 1): a model's flow
    # underestimates object motion. A 300-step small chain stabilised with the true poses (32 development
    # records, hysteresis 0.5, AP3D@0.5 static / moving camera): 0.007 / 0.004 at 1 m/s (its components are
    # fragments, the unlabelled size prior 2.0 × 1.0 m), 0.092 / 0.072 at 0.5, 0.753 / 0.461 at 0.25; the true
    # flow's boxes score the same at all three.
    min_speed: float = 0.25
    # m/s: a component whose voxels' mean velocity is slower is no moving object. Why: at the low voxel
    # threshold, slow components are mostly noise — above all where a stabilisation error (the egomotion
    # module's ~0.001 rad / 0.02 m) misaligns the static scene by a fraction of a voxel and the flow over
    # features turns that into 0.2–0.6 voxel of apparent motion. Why 1.0 (it was 0.5): on 32 held-out records
    # (`data generate --preset small --seed 7 --episodes 32 --frames 2 --moving-ego mixed`), flow over
    # contrastive features of the small report's 3 seeds, AP3D@0.5 rose at 1.0 for every seed, camera setting
    # and stabilisation (true poses: static 0.86/0.86/0.84 -> 0.91/0.89/0.86, moving 0.80/0.75/0.83 ->
    # 0.83/0.82/0.88; egomotion module: static 0.75/0.65/0.56 -> 0.84/0.78/0.73, moving 0.64/0.65/0.62 ->
    # 0.74/0.78/0.84); at 1.5 the static camera lost again. The boxes that match no mover move at 1.1-1.5
    # m/s (median), those that match at 3.0-3.6; the synthetic world's vehicles drive at 2-8 m/s. Regression
    # features gain too; flow over input volumes gains with the egomotion module but loses 0.03-0.09 with
    # exact poses on the static camera (README "Which voxels move" has the whole table).
    min_object_speed: float = 1.0
    min_voxels: int = 3             # smaller moving components are dropped
    occupied_above: float = 0.5     # occupancy probability above which a voxel holds matter
    shell_margin: float | None = None  # metres of the saliency shell (None: 2 voxels)
    nms_iou: float = 0.3            # BEV IoU above which a lower-scored box is dropped
    connectivity: int = 26
    # Which voxels hold matter for the boxes: "observed" — a depth point of frame 0 lies in the voxel
    # (and the occupancy head, which already zeroed the flow, agrees) — or "predicted", the occupancy
    # head alone (the paper's rule). The head also fills in unseen space, where the flow is noise.
    occupancy: str = "observed"
    # Voxels whose centre lies less than this many voxels above the ground plane fitted to frame 0's
    # depth points never move (core.moving.ground); None: no ground plane.
    ground_margin: float | None = DEFAULT_MARGIN_VOXELS
    # None: each box covers the voxels seen to move (the visible part of an object). A SizePrior: amodal
    # boxes of whole objects — oversized components split or dropped, boxes grown to the prior away from
    # the camera (core.moving.amodal).
    size_prior: SizePrior | None = None
    # What a voxel marked moving means (core.moving.detect_moving.MOVING_VOXEL_PAD): "surface" for flow over
    # the voxels that hold depth points (a model's, and the true flow of core.data.ground_truth: boxes of
    # their centres, unpadded), "centres" for a flow that moves exactly the voxels whose centres lie in an
    # object (padded one voxel).
    moving_voxels: str = "surface"
    # Voxels above this share of the speed threshold move when connected to one above it
    # (core.moving.detect_moving.DEFAULT_HYSTERESIS); 1: the threshold alone.
    hysteresis: float = DEFAULT_HYSTERESIS

    def __post_init__(self) -> None:
        if self.dt <= 0 or self.min_speed < 0 or self.min_object_speed < 0 or self.min_voxels < 1:
            raise ValueError(f"need dt > 0, min_speed ≥ 0, min_object_speed ≥ 0, min_voxels ≥ 1; got {self.dt}, "
                             f"{self.min_speed}, {self.min_object_speed}, {self.min_voxels}")
        check_options(moving_voxels=self.moving_voxels, hysteresis=self.hysteresis)
        if self.occupancy not in OCCUPANCY_SOURCES:
            raise ValueError(f"occupancy must be one of {OCCUPANCY_SOURCES}, got {self.occupancy!r}")

    def threshold_voxels(self, grid: GridConfig, speed: float | None = None) -> float:
        """Flow magnitude (voxels per step) of `speed` m/s (None: `min_speed`)."""
        return (self.min_speed if speed is None else speed) * self.dt / grid.voxel_size


@dataclass
class FrameEvidence:
    """What frame 0's depth alone says about the scene, in ref0: `observed` B×1×Z×Y×X in {0, 1} (voxels
    holding a depth point of any view), `ground` (one plane (4,) or None per item; core.moving.ground),
    `viewpoints` B×V×3 (the cameras' centres in ref0, metres: amodal boxes grow away from them) and
    `seen_by` B×V×Z×Y×X bool (the voxels holding a depth point of each view: a box grows away from the
    cameras that saw its component)."""

    observed: torch.Tensor
    ground: list
    viewpoints: torch.Tensor | None = None
    seen_by: torch.Tensor | None = None


def frame_evidence(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor, grid: GridConfig, *,
                   fit_ground: bool = True) -> FrameEvidence:
    """depth B×V×H×W (metres), pix_T_cam and cam_T_ref B×V×4×4 -> FrameEvidence in ref."""
    B, V, H, W = depth.shape
    xyz_cam, valid = depth_to_points(depth.reshape(B * V, H, W), pix_T_cam.reshape(B * V, 4, 4))  # BV×N×3, BV×N
    xyz_ref = se3.apply(se3.invert(cam_T_ref.reshape(B * V, 4, 4)), xyz_cam)  # BV×N×3
    xyz_ref, valid = xyz_ref.reshape(B, V * H * W, 3), valid.reshape(B, V * H * W)  # B×VN×3, B×VN
    seen_by = voxelize(xyz_ref.reshape(B * V, H * W, 3), grid, valid.reshape(B * V, H * W))  # BV×1×Z×Y×X
    seen_by = seen_by.reshape(B, V, *grid.shape_zyx) > 0                    # B×V×Z×Y×X
    observed = seen_by.any(dim=1, keepdim=True).to(xyz_ref.dtype)          # B×1×Z×Y×X
    planes = [fit_ground_plane(xyz_ref[b][valid[b]].double().cpu().numpy()) if fit_ground else None
              for b in range(B)]
    viewpoints = camera_centres(cam_T_ref)  # B×V×3
    return FrameEvidence(observed=observed, ground=planes, viewpoints=viewpoints, seen_by=seen_by)


def boxes_from_flow(flow: torch.Tensor, occupancy: torch.Tensor | None, grid: GridConfig,
                    config: MovingObjectsConfig | None = None, *, ground: list | None = None,
                    viewpoints: torch.Tensor | None = None, seen_by: torch.Tensor | None = None,
                    dt: float | Sequence[float] | None = None) -> dict[str, torch.Tensor]:
    """The post-processing alone, per batch item: flow B×3×Z×Y×X (voxels, stabilised), occupancy
    B×1×Z×Y×X probabilities or None (every voxel counts as occupied), ground: one plane or None per
    item (voxels within `config.ground_margin` voxels of it or below do not move), or None; viewpoints:
    B×V×3 camera centres in ref0 (amodal boxes grow away from the cameras that saw them: `seen_by`
    B×V×Z×Y×X bool, or None for the nearest camera), or None; dt: seconds from t0
    to t1, one per item or one for all (None: `config.dt`). The interval scales the velocities and the
    speed threshold, so pairs of a batch may span different intervals.

    Returns {"boxes": B×K×7 (ref0), "scores": B×K, "valid": B×K bool, "velocities": B×K×3 m/s} on
    flow's device, each item's rows best first (K ≥ 1; padding rows are zero and not valid).
    """
    cfg = config or MovingObjectsConfig()
    B = flow.shape[0]
    planes = ground if ground is not None and cfg.ground_margin is not None else [None] * B
    per_example = []
    for b in range(B):
        item = cfg if dt is None else replace(cfg, dt=float(dt if isinstance(dt, (int, float)) else dt[b]))
        per_example.append(moving_objects_from_flow(
            flow[b], None if occupancy is None else occupancy[b, 0], grid, threshold=item.threshold_voxels(grid),
            min_voxels=item.min_voxels, dt=item.dt, occupied_above=item.occupied_above,
            shell_margin=item.shell_margin, nms_iou=item.nms_iou, connectivity=item.connectivity,
            can_move=above_ground(grid, planes[b], margin_voxels=item.ground_margin or 0.0),
            size_prior=item.size_prior, viewpoints=None if viewpoints is None else viewpoints[b], ground=planes[b],
            moving_voxels=item.moving_voxels, seen_by=None if seen_by is None else seen_by[b],
            hysteresis=item.hysteresis, object_threshold=item.threshold_voxels(grid, item.min_object_speed)))
    return detections_to_tensors(per_example, device=flow.device)


def box_occupancy(config: MovingObjectsConfig, predicted: torch.Tensor | None,
                  evidence: FrameEvidence) -> torch.Tensor | None:
    """The occupancy the box post-processing uses (B×1×Z×Y×X): see MovingObjectsConfig.occupancy."""
    if config.occupancy == "predicted":
        return predicted
    # "observed": the flow is already zero where the head says free, so this is the intersection.
    return evidence.observed
