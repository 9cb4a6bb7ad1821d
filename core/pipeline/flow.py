"""3D imagination flow over a loaded bundle: two RGB-D rig frames -> flow in `ref0` (voxels, x y z, t -> t+1).

`flow_step` is the one pair step every flow consumer runs: frame 0's own-frame work (a FrameEncoding,
passed in when a stream kept it from the step before), the egomotion estimate when asked for or needed,
stabilisation (core.pipeline.stabilise: frame 1 re-lifted straight into ref0 with the estimate, the poses
or not at all), and the flow module. Flow of voxels the bundle's occupancy head calls free
(P(occupied) < `occupancy_threshold`) is set to zero (the paper's test-time rule), except, with `gate_fill`
> 0, within that many voxels of a moving occupied voxel (core.pipeline.flow_gate); without an occupancy
module the raw flow is returned. `estimate_flow` is the step without a cache, and moving objects
(core.pipeline.moving) add boxes to it. `ref_t` is `world_T_ref0/1` when given, else the camera of view 0
(see core.pipeline.egomotion).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from core.geometry import se3
from core.geometry.poses import rig_cam_T_ref
from core.models.egomotion_inputs import egomotion_fine_frame, egomotion_input_volume, fused_input_volume
from core.pipeline.egomotion import egomotion_from_volumes
from core.pipeline.encoding import FrameEncoding, Stopwatch, binary_volume, encode_previous
from core.pipeline.flow_gate import GATE_FILL, gate_flow
from core.pipeline.stabilise import STABILISE, identity_like, poses_ref0_T_ref1, resolve_stabilise

__all__ = ["STABILISE", "estimate_flow", "flow_pair", "flow_step"]


def flow_pair(flow_net, grid, *, features, rgb, depth, pix_T_cam, cam_T_ref0, volumes=None):
    """What the flow module compares, both in ref0: the mapper features (f0, f1) B×F×Z×Y×X, or — for a
    module trained on input volumes (`flow_net.inputs == "volume"`) — the fused occupancy+RGB input
    volumes B×4×Z×Y×X, frame 1 re-lifted into ref0 exactly like its features. `volumes` passes volumes
    already built (frame 0's egomotion input volume, on the same grid)."""
    if flow_net.inputs != "volume":
        return features
    if volumes is None:
        volumes = (None, None)
    v0 = volumes[0] if volumes[0] is not None else fused_input_volume(rgb[0], depth[0], pix_T_cam[0], cam_T_ref0[0], grid)
    v1 = volumes[1] if volumes[1] is not None else fused_input_volume(rgb[1], depth[1], pix_T_cam[1], cam_T_ref0[1], grid)
    return flow_net.pick_inputs(features=features, volumes=(v0, v1))


@torch.no_grad()
def flow_step(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
              world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor, pix_T_cam1: torch.Tensor,
              world_T_cam1: torch.Tensor, world_T_ref0: torch.Tensor | None = None,
              world_T_ref1: torch.Tensor | None = None, previous: FrameEncoding | None = None,
              current: FrameEncoding | None = None, ego_estimate: dict[str, torch.Tensor] | None = None,
              stabilize: str | None = None, egomotion: bool = True, evidence: bool = False,
              fit_ground: bool = True, occupancy_threshold: float = 0.5, features0: bool | None = None,
              gate_fill: int = GATE_FILL, timings: dict[str, float] | None = None) -> dict:
    """Inputs as `estimate_egomotion`, plus `previous`: frame 0's FrameEncoding kept from the step before
    (or None); current: frame 1's own-ref FrameEncoding when the caller made it already (a stream encodes
    each frame as it arrives, beside the step before; only its ego volume and encoding are read here);
    ego_estimate: this pair's `egomotion_from_volumes` answer when the caller made it already (a stream
    makes it beside the step before), else the egomotion module runs here;
    stabilize: "egomotion", "poses", "none" or None (egomotion when the bundle has it);
    egomotion: also estimate cam0_T_cam1 when the bundle can (stabilize="egomotion" always does);
    evidence / fit_ground: make frame 0's FrameEvidence (boxes need it); features0: make frame 0's mapper
    map even when nothing here reads it (None: only when needed, core.pipeline.encoding.needs_map);
    occupancy_threshold, gate_fill: the occupancy gate (core.pipeline.flow_gate.gate_flow's threshold, fill).

    Returns {"flow": B×3×Z×Y×X (free voxels zeroed), "flow_raw", "ref0_T_ref1": B×4×4 used to stabilise,
    "cam0_T_cam1": B×4×4 (only when the egomotion module ran), "features1": B×F×Z×Y×X in ref0 (only for a
    flow module that compares maps: one comparing input volumes never needs frame 1's map), "previous":
    frame 0's FrameEncoding, "current": frame 1's (`current` with its egomotion volume and encoding)}.
    `timings` receives seconds per stage: ego_volume, ego_encode, map_previous, flow_volume, flow_encode,
    evidence_previous, egomotion, map_current, flow.
    """
    stabilize = resolve_stabilise(bundle, stabilize)
    mapper, flow_net = bundle.require("mapper"), bundle.require("flow")
    run_ego = "egomotion" in bundle.modules and (egomotion or stabilize == "egomotion")
    enc0 = encode_previous(bundle, rgb=rgb0, depth=depth0, pix_T_cam=pix_T_cam0, world_T_cam=world_T_cam0,
                           world_T_ref=world_T_ref0, cached=previous, ego_volume=run_ego, evidence=evidence,
                           fit_ground=fit_ground, features=features0, timings=timings)
    watch = Stopwatch(timings)
    cam_T_ref0 = rig_cam_T_ref(world_T_cam0, world_T_ref0)  # B×V×4×4
    cam1_T_ref1 = rig_cam_T_ref(world_T_cam1, world_T_ref1)  # B×V×4×4
    current = FrameEncoding() if current is None else replace(current)
    out: dict = {"previous": enc0, "current": current}
    if run_ego:
        net = bundle.modules["egomotion"]
        if current.ego_volume is None:
            current.ego_volume = egomotion_input_volume(net, rgb1, depth1, pix_T_cam1, cam1_T_ref1)  # B×4×Z×Y×X
            watch.lap("ego_volume")
        if current.ego_fine is None:
            current.ego_fine = egomotion_fine_frame(net, depth1, pix_T_cam1, cam1_T_ref1)  # FineFrame or None
            watch.lap("ego_volume")
        if current.ego_features is None:
            current.ego_features = net.encode(current.ego_volume)  # B×F'×Z×Y×X, the next pair's reference
            watch.lap("ego_encode")
        ego = ego_estimate
        if ego is None:
            ego = egomotion_from_volumes(net, enc0.ego_volume, current.ego_volume, cam_T_ref0, cam1_T_ref1,
                                         features=(enc0.ego_features, current.ego_features),
                                         fine=(enc0.ego_fine, current.ego_fine))
        out["cam0_T_cam1"] = ego["cam0_T_cam1"]
        watch.lap("egomotion")
    if stabilize == "egomotion":
        ref0_T_ref1 = ego["ref0_T_ref1"]
    elif stabilize == "poses":
        ref0_T_ref1 = poses_ref0_T_ref1(world_T_cam0, world_T_cam1, world_T_ref0, world_T_ref1)
    else:
        ref0_T_ref1 = identity_like(world_T_cam0)
    cam1_T_ref0 = cam1_T_ref1 @ se3.invert(ref0_T_ref1)[:, None]  # B×V×4×4
    f1 = None
    if flow_net.inputs != "volume":  # a volume-input flow module never reads frame 1's map: skip the mapper
        f1 = out["features1"] = mapper(rgb1, depth1, pix_T_cam1, cam1_T_ref0)  # B×F×Z×Y×X, stabilised into ref0
        watch.lap("map_current")
    v0 = binary_volume(bundle, enc0)  # frame 0's binary input volume, when kept
    raw = flow_net(*flow_pair(flow_net, mapper.grid, features=(enc0.features, f1), rgb=(rgb0, rgb1),
                              depth=(depth0, depth1), pix_T_cam=(pix_T_cam0, pix_T_cam1),
                              cam_T_ref0=(cam_T_ref0, cam1_T_ref0),
                              volumes=(v0, None)),
                   encoded0=enc0.flow_encoded)["flow"]  # B×3×Z×Y×X
    flow = raw if enc0.occupancy is None else gate_flow(raw, enc0.occupancy, threshold=occupancy_threshold,
                                                         fill=gate_fill)
    watch.lap("flow")
    out.update(flow=flow, flow_raw=raw, ref0_T_ref1=ref0_T_ref1)
    return out


@torch.no_grad()
def estimate_flow(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                  world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                  pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                  world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                  stabilize: str = "poses", occupancy_threshold: float = 0.5,
                  gate_fill: int = GATE_FILL) -> dict[str, torch.Tensor]:
    """`flow_step` without a cache. Inputs as `estimate_egomotion`; stabilize "poses" (default),
    "egomotion" or "none". Returns `flow` B×3×Z×Y×X (free voxels zeroed), `flow_raw`, `ref0_T_ref1` B×4×4
    used for stabilisation, `features0` B×F×Z×Y×X (frame 0's map in ref0), `features1` (frame 1's,
    stabilised into ref0; only for a flow module that compares maps) and, with an occupancy module,
    `occupancy` B×1×Z×Y×X probabilities."""
    out = flow_step(bundle, rgb0=rgb0, depth0=depth0, pix_T_cam0=pix_T_cam0, world_T_cam0=world_T_cam0,
                    rgb1=rgb1, depth1=depth1, pix_T_cam1=pix_T_cam1, world_T_cam1=world_T_cam1,
                    world_T_ref0=world_T_ref0, world_T_ref1=world_T_ref1, stabilize=stabilize, egomotion=False,
                    occupancy_threshold=occupancy_threshold, gate_fill=gate_fill, features0=True)
    enc0 = out["previous"]
    result = {k: out[k] for k in ("flow", "flow_raw", "ref0_T_ref1", "features1") if k in out}
    result["features0"] = enc0.features
    if enc0.occupancy is not None:
        result["occupancy"] = enc0.occupancy
    return result
