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
from core.models.egomotion_inputs import egomotion_input_volume
from core.pipeline.moving_boxes import FrameEvidence, frame_evidence


@dataclass
class FrameEncoding:
    """One frame's inputs to a pair step, all in the frame's own `ref`.

    ego_volume: B×4×Z×Y×X egomotion input volume (None without an egomotion module or not made yet);
    features: B×F×Z×Y×X mapper map; occupancy: B×1×Z×Y×X probabilities (None without an occupancy head);
    evidence: what the frame's depth alone says (observed voxels, ground plane, viewpoints). A field is
    None until `encode_previous` filled it."""

    ego_volume: torch.Tensor | None = None
    features: torch.Tensor | None = None
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


@torch.no_grad()
def encode_previous(bundle, *, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                    world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None = None,
                    cached: FrameEncoding | None = None, ego_volume: bool = True, evidence: bool = True,
                    fit_ground: bool = True, timings: dict[str, float] | None = None) -> FrameEncoding:
    """Fill in what `cached` lacks of one frame's FrameEncoding (rgb B×V×3×H×W in [0,1], depth B×V×H×W,
    pix_T_cam/world_T_cam B×V×4×4, world_T_ref B×4×4 or None). `ego_volume`: make the egomotion input
    volume (when the bundle has an egomotion module); `evidence`: make the FrameEvidence (boxes need it;
    flow alone does not), fitting a ground plane when `fit_ground`. `timings` receives seconds per stage:
    ego_volume, map_previous, evidence_previous."""
    watch = Stopwatch(timings)
    enc = FrameEncoding() if cached is None else replace(cached)
    cam_T_ref = rig_cam_T_ref(world_T_cam, world_T_ref)  # B×V×4×4
    if ego_volume and enc.ego_volume is None and "egomotion" in bundle.modules:
        enc.ego_volume = egomotion_input_volume(bundle.modules["egomotion"], rgb, depth, pix_T_cam, cam_T_ref)
        watch.lap("ego_volume")
    if enc.features is None:
        enc.features = bundle.require("mapper")(rgb, depth, pix_T_cam, cam_T_ref)  # B×F×Z×Y×X
        if "occupancy" in bundle.modules:
            enc.occupancy = bundle.modules["occupancy"].probabilities(enc.features)  # B×1×Z×Y×X
        watch.lap("map_previous")
    if evidence and enc.evidence is None:
        enc.evidence = frame_evidence(depth, pix_T_cam, cam_T_ref, bundle.modules["mapper"].grid,
                                      fit_ground=fit_ground)
        watch.lap("evidence_previous")
    return enc
