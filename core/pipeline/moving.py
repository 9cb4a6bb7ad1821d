"""Unsupervised moving-object detection over a loaded bundle: two RGB-D rig frames -> scored boxes.

One computation, two ways to call it. `moving_step` runs the pair step (core.pipeline.flow.flow_step:
frame 0's own-frame work, egomotion once, stabilisation, 3D flow with free voxels zeroed) and the box
post-processing (core.pipeline.moving_boxes); given `previous`, frame 0's FrameEncoding kept from the step
before, it skips what that already holds. `moving_objects` is the stateless call: the same step without
a cache. Every transport goes through these two: the REST and gRPC unary routes call `moving_objects`,
the gRPC stream and the zenoh bridge call `moving_step` with their per-camera cache
(services.inference.camera_stream).

Steps (paper §3, moving objects): stabilise frame t+1 into `ref0` (with the bundle's egomotion estimate
when it has an `egomotion` module, else with the given poses), estimate 3D flow, then boxes from the
flow of the voxels frame 0's depth shows above its ground plane (core.pipeline.moving_boxes).

Frames (docs/conventions.md#frames): `ref0` is `world_T_ref0` when given, else the camera of view 0 at t0
(the inference services' convention). Boxes are canonical (x, y, z, lx, ly, lz, yaw) in ref0; velocities
are m/s along ref0's axes over `dt` seconds (per pair, or `config.dt`).
"""

from __future__ import annotations

from typing import Sequence

import torch

from core.pipeline.encoding import FrameEncoding, Stopwatch, encode_previous
from core.pipeline.flow import flow_step
# The post-processing's names, importable from here as before it had a file of its own.
from core.pipeline.moving_boxes import (BOXES_FRAME, DEFAULT_DT, OCCUPANCY_SOURCES, FrameEvidence,
                                        MovingObjectsConfig, box_occupancy, boxes_from_flow, frame_evidence)

__all__ = ["BOXES_FRAME", "DEFAULT_DT", "OCCUPANCY_SOURCES", "FrameEncoding", "FrameEvidence", "MovingObjectsConfig",
           "box_occupancy", "boxes_from_flow", "encode_previous", "frame_evidence", "moving_objects", "moving_step"]


@torch.no_grad()
def moving_step(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                previous: FrameEncoding | None = None, current: FrameEncoding | None = None,
                ego_estimate: dict[str, torch.Tensor] | None = None, stabilize: str | None = None,
                config: MovingObjectsConfig | None = None, dt: float | Sequence[float] | None = None,
                timings: dict[str, float] | None = None) -> dict:
    """rgb0/1: B×V×3×H×W in [0,1]; depth0/1: B×V×H×W metres; pix_T_cam0/1, world_T_cam0/1: B×V×4×4;
    world_T_ref0/1: B×4×4 or None (camera of view 0). previous: frame 0's FrameEncoding from the step
    before, or None; current, ego_estimate: frame 1's own-ref FrameEncoding and the pair's egomotion when
    made already (see core.pipeline.flow.flow_step). stabilize: "egomotion", "poses", "none" or None
    (egomotion when the bundle has it).
    dt: seconds from t0 to t1, one per batch item or one for all (None: `config.dt`).

    Returns {"boxes": B×K×7 canonical in ref0, "scores": B×K center-surround saliency in [−1, 1],
    "valid": B×K bool, "velocities": B×K×3 m/s in ref0, "flow": B×3×Z×Y×X (stabilised, free voxels
    zeroed), "ref0_T_ref1": B×4×4 used to stabilise, "cam0_T_cam1": B×4×4 (the egomotion route's answer;
    only with an egomotion module), "current": FrameEncoding of frame 1 (`current`, with its ego volume and
    encoding)}.
    `timings` (a dict) receives seconds per stage: ego_volume, map_previous, evidence_previous, egomotion,
    map_current (only for a flow module that compares feature maps), flow, boxes.
    """
    cfg = config or MovingObjectsConfig()
    out = flow_step(bundle, rgb0=rgb0, depth0=depth0, pix_T_cam0=pix_T_cam0, world_T_cam0=world_T_cam0,
                    rgb1=rgb1, depth1=depth1, pix_T_cam1=pix_T_cam1, world_T_cam1=world_T_cam1,
                    world_T_ref0=world_T_ref0, world_T_ref1=world_T_ref1, previous=previous, current=current,
                    ego_estimate=ego_estimate, stabilize=stabilize, evidence=True,
                    fit_ground=cfg.ground_margin is not None, occupancy_threshold=cfg.occupied_above, timings=timings)
    enc0 = out.pop("previous")
    watch = Stopwatch(timings)
    found = boxes_from_flow(out["flow"], box_occupancy(cfg, enc0.occupancy, enc0.evidence),
                            bundle.modules["mapper"].grid, cfg, ground=enc0.evidence.ground,
                            viewpoints=enc0.evidence.viewpoints, seen_by=enc0.evidence.seen_by, dt=dt)
    watch.lap("boxes")
    keep = ("flow", "ref0_T_ref1", "cam0_T_cam1", "current")
    return {**found, **{k: out[k] for k in keep if k in out}}


@torch.no_grad()
def moving_objects(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                   world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                   pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                   world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                   stabilize: str | None = None, config: MovingObjectsConfig | None = None,
                   dt: float | Sequence[float] | None = None) -> dict[str, torch.Tensor]:
    """`moving_step` without a cache (inputs and outputs as there, less `current`)."""
    out = moving_step(bundle, rgb0=rgb0, depth0=depth0, pix_T_cam0=pix_T_cam0, world_T_cam0=world_T_cam0,
                      rgb1=rgb1, depth1=depth1, pix_T_cam1=pix_T_cam1, world_T_cam1=world_T_cam1,
                      world_T_ref0=world_T_ref0, world_T_ref1=world_T_ref1, stabilize=stabilize, config=config, dt=dt)
    del out["current"]
    return out
