"""3D imagination flow inference: two RGB-D rig frames -> flow in `ref0` (voxels, x y z, t -> t+1).

Stabilisation (removing camera motion) re-unprojects frame 1 straight into ref0:
- `stabilize="poses"` (default): with the given poses, cam_T_ref0 = inv(world_T_cam1) · world_T_ref0;
- `stabilize="egomotion"`: with the bundle's egomotion estimate, cam_T_ref0 = cam_T_ref1 · inv(ref0_T_ref1).
`ref_t` is `world_T_ref0/1` when given, else the camera of view 0 (see core.pipeline.egomotion).
Flow of voxels the bundle's occupancy head calls free (P(occupied) < `occupancy_threshold`) is set to
zero (the paper's test-time rule); without an occupancy module the raw flow is returned.
"""

from __future__ import annotations

import torch

from core.errors import N3dmapError
from core.geometry import se3
from core.models.egomotion_inputs import fused_input_volume
from core.pipeline.egomotion import _module, estimate_egomotion, rig_cam_T_ref

STABILIZE = ("poses", "egomotion")


def flow_pair(flow_net, grid, *, features, rgb, depth, pix_T_cam, cam_T_ref0, volumes=None):
    """What the flow module compares, both in ref0: the mapper features (f0, f1) B×F×Z×Y×X, or — for a
    module trained on input volumes (`flow_net.inputs == "volume"`) — the fused occupancy+RGB input
    volumes B×4×Z×Y×X, frame 1 re-lifted into ref0 exactly like its features. `volumes` passes volumes
    already built (the stream step caches frame 0's)."""
    if flow_net.inputs != "volume":
        return features
    if volumes is None:
        volumes = (None, None)
    v0 = volumes[0] if volumes[0] is not None else fused_input_volume(rgb[0], depth[0], pix_T_cam[0], cam_T_ref0[0], grid)
    v1 = volumes[1] if volumes[1] is not None else fused_input_volume(rgb[1], depth[1], pix_T_cam[1], cam_T_ref0[1], grid)
    return flow_net.pick_inputs(features=features, volumes=(v0, v1))


@torch.no_grad()
def estimate_flow(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                  world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                  pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                  world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                  stabilize: str = "poses", occupancy_threshold: float = 0.5) -> dict[str, torch.Tensor]:
    """Inputs as `estimate_egomotion`. Returns `flow` B×3×Z×Y×X (free voxels zeroed), `flow_raw`,
    `ref0_T_ref1` B×4×4 used for stabilisation, `features0`/`features1` B×F×Z×Y×X (both in ref0) and,
    with an occupancy module, `occupancy` B×1×Z×Y×X probabilities."""
    if stabilize not in STABILIZE:
        raise N3dmapError(f"stabilize must be one of {STABILIZE}, got {stabilize!r}")
    mapper, flow_net = _module(bundle, "mapper"), _module(bundle, "flow")
    cam_T_ref0 = rig_cam_T_ref(world_T_cam0, world_T_ref0)  # B×V×4×4
    if stabilize == "poses":
        ref0 = world_T_cam0[:, 0] if world_T_ref0 is None else world_T_ref0
        ref1 = world_T_cam1[:, 0] if world_T_ref1 is None else world_T_ref1
        ref0_T_ref1 = se3.compose(se3.invert(ref0), ref1)
    else:
        ref0_T_ref1 = estimate_egomotion(
            bundle, rgb0=rgb0, depth0=depth0, pix_T_cam0=pix_T_cam0, world_T_cam0=world_T_cam0, rgb1=rgb1,
            depth1=depth1, pix_T_cam1=pix_T_cam1, world_T_cam1=world_T_cam1, world_T_ref0=world_T_ref0,
            world_T_ref1=world_T_ref1)["ref0_T_ref1"]
    cam1_T_ref1 = rig_cam_T_ref(world_T_cam1, world_T_ref1)  # B×V×4×4
    cam1_T_ref0 = cam1_T_ref1 @ se3.invert(ref0_T_ref1)[:, None]  # B×V×4×4
    f0 = mapper(rgb0, depth0, pix_T_cam0, cam_T_ref0)  # B×F×Z×Y×X
    f1 = mapper(rgb1, depth1, pix_T_cam1, cam1_T_ref0)  # B×F×Z×Y×X, stabilised into ref0
    raw = flow_net(*flow_pair(flow_net, bundle.preset.grid, features=(f0, f1), rgb=(rgb0, rgb1),
                              depth=(depth0, depth1), pix_T_cam=(pix_T_cam0, pix_T_cam1),
                              cam_T_ref0=(cam_T_ref0, cam1_T_ref0)))["flow"]  # B×3×Z×Y×X
    out = {"flow_raw": raw, "flow": raw, "ref0_T_ref1": ref0_T_ref1, "features0": f0, "features1": f1}
    if "occupancy" in bundle.modules:
        prob = bundle.modules["occupancy"].probabilities(f0)  # B×1×Z×Y×X
        out["occupancy"] = prob
        out["flow"] = raw * (prob >= occupancy_threshold).to(raw.dtype)
    return out
