"""One frame's own-frame work for a pair step, made once and reusable as the next pair's frame 0.

What a pair step (core.pipeline.flow.flow_step) needs of its frame 0 depends only on that frame, in its
own `ref` (never stabilised): the egomotion input volume, the mapper's feature map and the occupancy
head's probabilities, and what its depth alone says (core.pipeline.moving_boxes.FrameEvidence). A stream
keeps it from one step to the next (frame t is frame 0 of the pair t -> t+1) and may make it while it
waits for the next frame; a stateless call makes it from scratch. Either way the same code runs on the
same inputs, so the answers are equal.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import torch

from core.geometry.poses import rig_cam_T_ref
from core.models.egomotion_fine import FineFrame
from core.models.egomotion_inputs import egomotion_fine_frame, egomotion_input_volume, fused_input_volume
from core.pipeline.moving_boxes import FrameEvidence, frame_evidence


@dataclass
class FrameEncoding:
    """One frame's inputs to a pair step, all in the frame's own `ref`.

    ego_volume: B×4×Z×Y×X egomotion input volume (None without an egomotion module or not made yet);
    ego_features: B×F'×Z×Y×X the egomotion module's encoding of it (EgomotionNet.encode), so each frame is
    encoded once on a stream; ego_fine: the frame's data for the module's fine stage (a FineFrame: its TSDF
    and points, or its splat; None without one: core.models.egomotion_fine); features: B×F×Z×Y×X mapper map (None when nothing in the pair step reads it:
    see `needs_map`); occupancy: B×1×Z×Y×X probabilities (None without an occupancy head);
    flow_encoded: B×C×Z×Y×X the flow module's encoding of what it compares of this frame (Flow3D.encode of
    the map, or of the binary input volume when the flow module compares input volumes); flow_volume:
    B×4×Z×Y×X that binary input volume on the mapper's grid where it is not the ego volume;
    evidence: what the frame's depth alone says (observed voxels, ground plane, viewpoints). A field is
    None until `encode_previous` filled it."""

    ego_volume: torch.Tensor | None = None
    ego_features: torch.Tensor | None = None
    ego_fine: FineFrame | None = None
    features: torch.Tensor | None = None
    flow_encoded: torch.Tensor | None = None
    flow_volume: torch.Tensor | None = None
    occupancy: torch.Tensor | None = None
    evidence: FrameEvidence | None = None


class Stopwatch:
    """Adds the seconds of each named stage to `timings` (when given)."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings, self.last = timings, time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[stage] = self.timings.get(stage, 0.0) + now - self.last
        self.last = now


def needs_map(bundle) -> bool:
    """Whether a pair step reads frame 0's mapper map: for an occupancy head's gate, or for a flow module
    that compares maps. A flow module over input volumes without an occupancy head never does, and the
    mapper is the largest part of the frame's own work (small preset, 1 thread: ~16–37 ms of a step)."""
    flow = bundle.modules.get("flow")
    return "occupancy" in bundle.modules or flow is None or getattr(flow, "inputs", "features") != "volume"


def shares_ego_volume(bundle) -> bool:
    """Whether a flow module over input volumes can read the egomotion module's input volume: the same grid
    and binary occupancy (an egomotion module on splatted occupancy has its own volume)."""
    ego = bundle.modules.get("egomotion")
    return (ego is not None and ego.grid == bundle.modules["mapper"].grid
            and getattr(ego, "input_occupancy", "binary") == "binary")


def binary_volume(bundle, enc: FrameEncoding) -> torch.Tensor | None:
    """The frame's binary input volume on the mapper's grid, if `enc` holds it: the egomotion module's where
    `shares_ego_volume`, else the flow's own `flow_volume`."""
    return enc.ego_volume if shares_ego_volume(bundle) else enc.flow_volume


def flow_input(bundle, enc: FrameEncoding) -> torch.Tensor | None:
    """What the flow module compares of this frame, in its own ref, if `enc` holds it: the map, or the
    binary input volume (`binary_volume`); None otherwise."""
    flow = bundle.modules.get("flow")
    if flow is None:
        return None
    return enc.features if flow.inputs != "volume" else binary_volume(bundle, enc)


def is_complete(enc: FrameEncoding | None, bundle, *, evidence: bool = True) -> bool:
    """Whether `enc` already holds everything a pair step over `bundle` needs of its frame 0."""
    if enc is None:
        return False
    if "egomotion" in bundle.modules and (enc.ego_volume is None or enc.ego_features is None or (
            enc.ego_fine is None and bundle.modules["egomotion"].fine_grid is not None)):
        return False
    if needs_map(bundle) and enc.features is None:
        return False
    if enc.flow_encoded is None and flow_input(bundle, enc) is not None:
        return False
    return not evidence or enc.evidence is not None


@torch.no_grad()
def encode_previous(bundle, *, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                    world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None = None,
                    cached: FrameEncoding | None = None, ego_volume: bool = True, evidence: bool = True,
                    fit_ground: bool = True, features: bool | None = None, flow_encoding: bool = True,
                    timings: dict[str, float] | None = None) -> FrameEncoding:
    """Fill in what `cached` lacks of one frame's FrameEncoding (rgb B×V×3×H×W in [0,1], depth B×V×H×W,
    pix_T_cam/world_T_cam B×V×4×4, world_T_ref B×4×4 or None). `ego_volume`: make the egomotion input
    volume and its encoding (when the bundle has an egomotion module); `evidence`: make the FrameEvidence
    (boxes need it; flow alone does not), fitting a ground plane when `fit_ground`; `features`: make the
    mapper map (and occupancy), None = only when a pair step reads it (`needs_map`); `flow_encoding`: make
    the flow module's encoding of the frame (what it compares when the frame is a pair's frame 0).
    `timings` receives seconds per stage: ego_volume, ego_encode, map_previous, flow_volume, flow_encode,
    evidence_previous."""
    watch = Stopwatch(timings)
    enc = FrameEncoding() if cached is None else replace(cached)
    cam_T_ref = rig_cam_T_ref(world_T_cam, world_T_ref)  # B×V×4×4
    if ego_volume and enc.ego_volume is None and "egomotion" in bundle.modules:
        enc.ego_volume = egomotion_input_volume(bundle.modules["egomotion"], rgb, depth, pix_T_cam, cam_T_ref)
        watch.lap("ego_volume")
    if ego_volume and enc.ego_fine is None and "egomotion" in bundle.modules:
        enc.ego_fine = egomotion_fine_frame(bundle.modules["egomotion"], depth, pix_T_cam, cam_T_ref)  # or None
        watch.lap("ego_volume")
    if ego_volume and enc.ego_features is None and enc.ego_volume is not None:
        enc.ego_features = bundle.modules["egomotion"].encode(enc.ego_volume)  # B×F'×Z×Y×X
        watch.lap("ego_encode")
    if features is None:
        features = needs_map(bundle)
    if features and enc.features is None:
        enc.features = bundle.require("mapper")(rgb, depth, pix_T_cam, cam_T_ref)  # B×F×Z×Y×X
        if "occupancy" in bundle.modules:
            enc.occupancy = bundle.modules["occupancy"].probabilities(enc.features)  # B×1×Z×Y×X
        watch.lap("map_previous")
    flow = bundle.modules.get("flow")
    if (flow_encoding and flow is not None and flow.inputs == "volume" and not shares_ego_volume(bundle)
            and enc.flow_volume is None):
        enc.flow_volume = fused_input_volume(rgb, depth, pix_T_cam, cam_T_ref, bundle.modules["mapper"].grid)
        watch.lap("flow_volume")
    if flow_encoding and enc.flow_encoded is None and (flow_in := flow_input(bundle, enc)) is not None:
        enc.flow_encoded = bundle.modules["flow"].encode(flow_in)  # B×C×Z×Y×X
        watch.lap("flow_encode")
    if evidence and enc.evidence is None:
        enc.evidence = frame_evidence(depth, pix_T_cam, cam_T_ref, bundle.modules["mapper"].grid,
                                      fit_ground=fit_ground)
        watch.lap("evidence_previous")
    return enc
