"""One streaming step of moving-object detection: frame t-1 and frame t -> egomotion and boxes, with
frame t-1's own-frame work reused from the step before.

The inference routes answer one pair at a time and share nothing: the stream bridge used to call
`estimate_egomotion` (for the egomotion stream) and then `moving_objects`, which estimated the same
egomotion again for stabilisation, and re-encoded the previous frame that the step before had already
lifted. Here one pass gives both, and what frame t contributes as the *previous* frame of the next
step (its egomotion input volume, its feature map and occupancy in its own `ref`) comes back as a
`FrameEncoding` to pass in next time. Results equal the route calls (tests/unit/streaming compares
them): the same functions run on the same inputs, only fewer times.

Frames (docs/conventions.md#frames): `ref_t` is `world_T_ref_t` when given, else the camera of view 0 at t, as in
core.pipeline.egomotion. Boxes are canonical rows in ref0 (the camera at t-1 for the bridge).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from core.errors import BundleError
from core.geometry import se3
from core.models.egomotion_inputs import fused_input_volume
from core.pipeline.flow import flow_pair
from core.pipeline.egomotion import rig_cam_T_ref
from core.pipeline.moving import FrameEvidence, MovingObjectsConfig, box_occupancy, boxes_from_flow, frame_evidence


@dataclass
class FrameEncoding:
    """One frame's inputs to the next step, all in the frame's own `ref` (never stabilised).

    ego_volume: B×4×Z×Y×X egomotion input volume (None without an egomotion module or not yet made);
    features: B×F×Z×Y×X mapper map; occupancy: B×1×Z×Y×X probabilities (None without an occupancy
    head); evidence: what the frame's depth alone says. `features`/`occupancy`/`evidence` are None until
    `encode_previous` filled them."""

    ego_volume: torch.Tensor | None = None
    features: torch.Tensor | None = None
    occupancy: torch.Tensor | None = None
    evidence: FrameEvidence | None = None  # observed voxels and ground plane (core.pipeline.moving)


class _Stopwatch:
    """Adds the seconds of each named stage to `timings` (when given)."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings, self.last = timings, time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[stage] = self.timings.get(stage, 0.0) + now - self.last
        self.last = now


def _check_modules(bundle) -> None:
    if "flow" not in bundle.modules or "mapper" not in bundle.modules:
        raise BundleError(f"moving objects need the bundle's 'mapper' and 'flow' modules; it holds "
                          f"{sorted(bundle.modules)}")


@torch.no_grad()
def encode_previous(bundle, *, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                    world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None = None,
                    cached: FrameEncoding | None = None,
                    timings: dict[str, float] | None = None) -> FrameEncoding:
    """Fill in what `cached` lacks of one frame's `FrameEncoding` (rgb B×V×3×H×W in [0,1], depth
    B×V×H×W, pix_T_cam/world_T_cam B×V×4×4, world_T_ref B×4×4 or None). A bridge calls this while it
    waits for the next frame, so that work leaves the next step's latency; `moving_step` calls it for
    whatever is still missing."""
    watch = _Stopwatch(timings)
    enc = FrameEncoding() if cached is None else FrameEncoding(cached.ego_volume, cached.features, cached.occupancy,
                                                               cached.evidence)
    cam_T_ref = rig_cam_T_ref(world_T_cam, world_T_ref)  # B×V×4×4
    if enc.ego_volume is None and "egomotion" in bundle.modules:
        enc.ego_volume = fused_input_volume(rgb, depth, pix_T_cam, cam_T_ref, bundle.modules["egomotion"].grid)
        watch.lap("ego_volume")
    if enc.features is None:
        enc.features = bundle.modules["mapper"](rgb, depth, pix_T_cam, cam_T_ref)  # B×F×Z×Y×X
        if "occupancy" in bundle.modules:
            enc.occupancy = bundle.modules["occupancy"].probabilities(enc.features)  # B×1×Z×Y×X
        watch.lap("map_previous")
    if enc.evidence is None:
        enc.evidence = frame_evidence(depth, pix_T_cam, cam_T_ref, bundle.modules["mapper"].grid)
        watch.lap("evidence_previous")
    return enc


@torch.no_grad()
def moving_step(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                world_T_ref0: torch.Tensor | None = None, world_T_ref1: torch.Tensor | None = None,
                previous: FrameEncoding | None = None, stabilize: str | None = None,
                config: MovingObjectsConfig | None = None,
                timings: dict[str, float] | None = None) -> dict:
    """Inputs as core.pipeline.moving.moving_objects, plus `previous`: frame 0's FrameEncoding from
    the step before (or None). stabilize: "egomotion", "poses" or None (egomotion when the bundle has it).

    Returns {"boxes": B×K×7 in ref0, "scores": B×K, "valid": B×K, "velocities": B×K×3 m/s, "flow":
    B×3×Z×Y×X, "ref0_T_ref1": B×4×4 used to stabilise, "cam0_T_cam1": B×4×4 (the egomotion route's
    answer; only with an egomotion module), "current": FrameEncoding of frame 1 (its ego volume only)}.
    `timings` (a dict) receives seconds per stage: ego_volume, map_previous, evidence_previous, egomotion, map_current
    (only for a flow module that compares feature maps), flow, boxes.
    """
    _check_modules(bundle)
    if stabilize is None:
        stabilize = "egomotion" if "egomotion" in bundle.modules else "poses"
    if stabilize not in ("egomotion", "poses"):
        raise BundleError(f"stabilize must be 'egomotion' or 'poses', got {stabilize!r}")
    has_ego = "egomotion" in bundle.modules
    cfg = config or MovingObjectsConfig()
    enc0 = encode_previous(bundle, rgb=rgb0, depth=depth0, pix_T_cam=pix_T_cam0, world_T_cam=world_T_cam0,
                           world_T_ref=world_T_ref0, cached=previous, timings=timings)
    watch = _Stopwatch(timings)
    cam_T_ref0 = rig_cam_T_ref(world_T_cam0, world_T_ref0)  # B×V×4×4
    cam1_T_ref1 = rig_cam_T_ref(world_T_cam1, world_T_ref1)  # B×V×4×4
    out: dict = {"current": FrameEncoding()}
    ego_T = None
    if has_ego:
        net = bundle.modules["egomotion"]
        vol1 = fused_input_volume(rgb1, depth1, pix_T_cam1, cam1_T_ref1, net.grid)  # B×4×Z×Y×X
        out["current"].ego_volume = vol1
        watch.lap("ego_volume")
        ego_T = net(enc0.ego_volume, vol1)["ref0_T_ref1"]  # B×4×4
        out["cam0_T_cam1"] = cam_T_ref0[:, 0] @ ego_T @ se3.invert(cam1_T_ref1[:, 0])  # B×4×4
        watch.lap("egomotion")
    if stabilize == "egomotion":
        if ego_T is None:
            raise BundleError(f"stabilize='egomotion' needs an 'egomotion' module; the bundle holds "
                              f"{sorted(bundle.modules)}")
        ref0_T_ref1 = ego_T
    else:
        ref0 = world_T_cam0[:, 0] if world_T_ref0 is None else world_T_ref0
        ref1 = world_T_cam1[:, 0] if world_T_ref1 is None else world_T_ref1
        ref0_T_ref1 = se3.compose(se3.invert(ref0), ref1)
    cam1_T_ref0 = cam1_T_ref1 @ se3.invert(ref0_T_ref1)[:, None]  # B×V×4×4
    flow_net, grid = bundle.modules["flow"], bundle.modules["mapper"].grid
    f1 = None
    if flow_net.inputs != "volume":  # a volume-input flow module never reads frame 1's map: skip the mapper
        f1 = bundle.modules["mapper"](rgb1, depth1, pix_T_cam1, cam1_T_ref0)  # B×F×Z×Y×X, stabilised into ref0
        watch.lap("map_current")
    # Frame 0's egomotion input volume is the flow's v0 too when the module compares input volumes.
    same_grid = "egomotion" in bundle.modules and bundle.modules["egomotion"].grid == grid
    v0 = enc0.ego_volume if same_grid else None
    raw = flow_net(*flow_pair(flow_net, grid, features=(enc0.features, f1), rgb=(rgb0, rgb1), depth=(depth0, depth1),
                              pix_T_cam=(pix_T_cam0, pix_T_cam1), cam_T_ref0=(cam_T_ref0, cam1_T_ref0),
                              volumes=(v0, None)))["flow"]  # B×3×Z×Y×X
    flow = raw if enc0.occupancy is None else raw * (enc0.occupancy >= cfg.occupied_above).to(raw.dtype)
    watch.lap("flow")
    found = boxes_from_flow(flow, box_occupancy(cfg, enc0.occupancy, enc0.evidence), grid, cfg,
                            ground=enc0.evidence.ground, viewpoints=enc0.evidence.viewpoints)
    watch.lap("boxes")
    out.update(found, flow=flow, ref0_T_ref1=ref0_T_ref1)
    return out
