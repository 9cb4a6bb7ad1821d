"""Unsupervised moving-object detection over a loaded bundle: two RGB-D rig frames -> scored boxes.

Steps (paper §3, moving objects): stabilise frame t+1 into `ref0` (with the bundle's egomotion
estimate when it has an `egomotion` module, else with the given poses), estimate 3D flow
(core.pipeline.flow.estimate_flow, which zeroes the flow of voxels the occupancy head calls free),
then per example threshold the flow magnitude, take 3D connected components, score each by
center-surround motion saliency, fit an oriented box, and suppress overlaps
(core.moving.detect_moving.moving_objects_from_flow).

Frames (DESIGN.md §2): `ref0` is `world_T_ref0` when given, else the camera of view 0 at t0 (the
inference services' convention). Boxes are canonical (x, y, z, lx, ly, lz, yaw) in ref0; velocities
are m/s along ref0's axes. Flow is B×3×Z×Y×X in voxels, channels (x, y, z), t0 -> t1.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from core.errors import BundleError
from core.geometry.grid import GridConfig
from core.moving.detect_moving import detections_to_tensors, moving_objects_from_flow
from core.pipeline.flow import estimate_flow

BOXES_FRAME = "ref0"
# Seconds between the two frames when the caller does not say: the built-in synthetic world's step
# (core.synthetic.config.WorldConfig.dt). Only the velocities' scale and the speed threshold use it.
DEFAULT_DT = 0.2


@dataclass(frozen=True)
class MovingObjectsConfig:
    """Post-processing of the stabilised flow into boxes (see moving_objects_from_flow)."""

    dt: float = DEFAULT_DT          # seconds from t0 to t1
    min_speed: float = 1.0          # m/s: voxels whose flow is slower do not move
    min_voxels: int = 3             # smaller moving components are dropped
    occupied_above: float = 0.5     # occupancy probability above which a voxel holds matter
    shell_margin: float | None = None  # metres of the saliency shell (None: 2 voxels)
    nms_iou: float = 0.3            # BEV IoU above which a lower-scored box is dropped
    connectivity: int = 26

    def __post_init__(self) -> None:
        if self.dt <= 0 or self.min_speed < 0 or self.min_voxels < 1:
            raise ValueError(f"need dt > 0, min_speed ≥ 0, min_voxels ≥ 1; got {self.dt}, {self.min_speed}, "
                             f"{self.min_voxels}")

    def threshold_voxels(self, grid: GridConfig) -> float:
        """Flow magnitude (voxels per step) of `min_speed`."""
        return self.min_speed * self.dt / grid.voxel_size


def boxes_from_flow(flow: torch.Tensor, occupancy: torch.Tensor | None, grid: GridConfig,
                    config: MovingObjectsConfig | None = None) -> dict[str, torch.Tensor]:
    """The post-processing alone, per batch item: flow B×3×Z×Y×X (voxels, stabilised), occupancy
    B×1×Z×Y×X probabilities or None (every voxel counts as occupied).

    Returns {"boxes": B×K×7 (ref0), "scores": B×K, "valid": B×K bool, "velocities": B×K×3 m/s} on
    flow's device, each item's rows best first (K ≥ 1; padding rows are zero and not valid).
    """
    cfg = config or MovingObjectsConfig()
    per_example = [
        moving_objects_from_flow(flow[b], None if occupancy is None else occupancy[b, 0], grid,
                                 threshold=cfg.threshold_voxels(grid), min_voxels=cfg.min_voxels, dt=cfg.dt,
                                 occupied_above=cfg.occupied_above, shell_margin=cfg.shell_margin,
                                 nms_iou=cfg.nms_iou, connectivity=cfg.connectivity)
        for b in range(flow.shape[0])]
    return detections_to_tensors(per_example, device=flow.device)


@torch.no_grad()
def moving_objects(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                   world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                   pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                   world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                   stabilize: str | None = None, config: MovingObjectsConfig | None = None) -> dict[str, torch.Tensor]:
    """rgb0/1: B×V×3×H×W in [0,1]; depth0/1: B×V×H×W metres; pix_T_cam0/1, world_T_cam0/1: B×V×4×4;
    world_T_ref0/1: B×4×4 or None (camera of view 0). stabilize: "egomotion", "poses" or None (the
    bundle's egomotion module when it has one, else the poses).

    Returns {"boxes": B×K×7 canonical in ref0, "scores": B×K center-surround saliency in [−1, 1],
    "valid": B×K bool, "velocities": B×K×3 m/s in ref0, "flow": B×3×Z×Y×X (stabilised, free voxels
    zeroed), "ref0_T_ref1": B×4×4 used to stabilise}.
    """
    if stabilize is None:
        stabilize = "egomotion" if "egomotion" in bundle.modules else "poses"
    cfg = config or MovingObjectsConfig()
    if "flow" not in bundle.modules or "mapper" not in bundle.modules:
        raise BundleError(f"moving objects need the bundle's 'mapper' and 'flow' modules; it holds "
                          f"{sorted(bundle.modules)}")
    out = estimate_flow(bundle, rgb0=rgb0, depth0=depth0, pix_T_cam0=pix_T_cam0, world_T_cam0=world_T_cam0,
                        rgb1=rgb1, depth1=depth1, pix_T_cam1=pix_T_cam1, world_T_cam1=world_T_cam1,
                        world_T_ref0=world_T_ref0, world_T_ref1=world_T_ref1, stabilize=stabilize,
                        occupancy_threshold=cfg.occupied_above)
    grid = bundle.modules["mapper"].grid
    found = boxes_from_flow(out["flow"], out.get("occupancy"), grid, cfg)
    return {**found, "flow": out["flow"], "ref0_T_ref1": out["ref0_T_ref1"]}
