"""The slow, obvious moving-object pair: every stage written out from the modules, nothing cached or skipped.

core.pipeline.moving.moving_step reuses frame 0's encoding, shares frame 0's egomotion volume with a
volume-input flow module, skips frame 1's map when the flow module never reads it, and estimates egomotion
once for both stabilisation and `cam0_T_cam1`. This reference does none of that: egomotion through
core.pipeline.estimate_egomotion (which builds both volumes itself), both frames mapped into ref0, the
flow module's inputs built from scratch, the occupancy gate, frame 0's evidence and the box
post-processing (core.pipeline.moving_boxes, checked on ground truth in tests/unit/pipeline). `ref_t` is
the camera of view 0 at t, as in the services.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from core.geometry import se3
from core.geometry.poses import rig_cam_T_ref
from core.models.egomotion_inputs import fused_input_volume
from core.pipeline.egomotion import estimate_egomotion
from core.pipeline.moving_boxes import MovingObjectsConfig, boxes_from_flow, frame_evidence


@torch.no_grad()
def reference_moving_objects(bundle, pair: dict, *, stabilize: str, dt: float,
                             config: MovingObjectsConfig | None = None, world_T_ref0=None, world_T_ref1=None) -> dict:
    """pair: the keywords of core.pipeline.moving_objects (rgb0, ..., world_T_cam1); world_T_ref0/1: B×4×4
    map frames (None: the cameras of view 0).
    stabilize: "egomotion" or "poses". Returns boxes, scores, valid, velocities, flow, ref0_T_ref1 and,
    with an egomotion module, cam0_T_cam1 (all as moving_step returns them)."""
    cfg = replace(config or MovingObjectsConfig(), dt=dt)
    mapper, flow_net, grid = bundle.modules["mapper"], bundle.modules["flow"], bundle.modules["mapper"].grid
    ego = (estimate_egomotion(bundle, **pair, world_T_ref0=world_T_ref0, world_T_ref1=world_T_ref1)
           if "egomotion" in bundle.modules else {})
    world_T_ref0 = pair["world_T_cam0"][:, 0] if world_T_ref0 is None else world_T_ref0  # B×4×4
    world_T_ref1 = pair["world_T_cam1"][:, 0] if world_T_ref1 is None else world_T_ref1
    if stabilize == "egomotion":
        ref0_T_ref1 = ego["ref0_T_ref1"]
    else:  # ref0_T_ref1 = inv(world_T_ref0) · world_T_ref1
        ref0_T_ref1 = se3.invert(world_T_ref0) @ world_T_ref1
    cam0_T_ref0 = rig_cam_T_ref(pair["world_T_cam0"], world_T_ref0)                                   # B×V×4×4
    cam1_T_ref0 = rig_cam_T_ref(pair["world_T_cam1"], world_T_ref1) @ se3.invert(ref0_T_ref1)[:, None]  # B×V×4×4
    f0 = mapper(pair["rgb0"], pair["depth0"], pair["pix_T_cam0"], cam0_T_ref0)
    f1 = mapper(pair["rgb1"], pair["depth1"], pair["pix_T_cam1"], cam1_T_ref0)
    if flow_net.inputs == "volume":
        v0 = fused_input_volume(pair["rgb0"], pair["depth0"], pair["pix_T_cam0"], cam0_T_ref0, grid)
        v1 = fused_input_volume(pair["rgb1"], pair["depth1"], pair["pix_T_cam1"], cam1_T_ref0, grid)
        inputs = flow_net.pick_inputs(features=(f0, f1), volumes=(v0, v1))
    else:
        inputs = (f0, f1)
    flow = flow_net(*inputs)["flow"]
    if "occupancy" in bundle.modules:
        flow = flow * (bundle.modules["occupancy"].probabilities(f0) >= cfg.occupied_above).to(flow.dtype)
    evidence = frame_evidence(pair["depth0"], pair["pix_T_cam0"], cam0_T_ref0, grid)
    assert cfg.occupancy == "observed"  # the only box occupancy the services use
    out = boxes_from_flow(flow, evidence.observed, grid, cfg, ground=evidence.ground, viewpoints=evidence.viewpoints,
                          seen_by=evidence.seen_by)
    out.update(flow=flow, ref0_T_ref1=ref0_T_ref1)
    if "cam0_T_cam1" in ego:
        out["cam0_T_cam1"] = ego["cam0_T_cam1"]
    return out
