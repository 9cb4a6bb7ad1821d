"""Occupancy accuracy on labelled voxels (the paper's appendix protocol).

Per record and step t: the map is built from ONE view (`input_view`), and the labels are the union of
that view's and the next view's (occupied = voxelised points, free = ray traversal; unlabelled voxels
are ignored). Scores: accuracy for occupied / free / all labelled voxels and occupied IoU (definitions:
core.eval.occupancy_metrics).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from core.data.ground_truth import gt_free, gt_occupancy
from core.errors import ConfigError
from core.eval.occupancy_metrics import add_counts, occupancy_counts, occupancy_scores
from core.eval.protocols.inputs import record_batch
from core.tasks.poses import cam_T_ref

NEEDS = ("mapper", "occupancy")


@dataclass(frozen=True, kw_only=True)
class OccupancyEvalConfig:
    input_view: int = 0       # the single view the map is built from
    threshold: float = 0.5    # P(occupied) above which a voxel counts as occupied


@torch.no_grad()
def evaluate(bundle, records, config: OccupancyEvalConfig = OccupancyEvalConfig(), *, device) -> dict:
    """{"scores": core.eval.occupancy_metrics.occupancy_scores, "frames", "example": {"prob", "occ",
    "input"} Z×Y×X arrays of the first frame (prediction, occupied labels, the input view's points)}."""
    grid = bundle.preset.grid
    mapper, head = bundle.modules["mapper"], bundle.modules["occupancy"]
    input_view = config.input_view
    counts: dict = {}
    example = None
    frames = 0
    for record in records:
        batch = record_batch(record, device)
        T, V = batch["rgb"].shape[1:3]
        if not 0 <= input_view < V:
            raise ConfigError(f"--input-view {input_view}: records have {V} views")
        label_views = sorted({input_view, (input_view + 1) % V})
        v = [input_view]
        for t in range(T):
            cam = cam_T_ref(batch, t, t)  # 1×V×4×4
            features = mapper(batch["rgb"][:, t][:, v], batch["depth"][:, t][:, v], batch["pix_T_cam"][:, v], cam[:, v])
            prob = head.probabilities(features)  # 1×1×Z×Y×X
            occ = gt_occupancy(record, t, grid, label_views)[None].to(device) > 0.5
            free = gt_free(record, t, grid, label_views)[None].to(device) > 0.5
            counts = add_counts(counts, occupancy_counts(prob, occ, free, threshold=config.threshold))
            frames += 1
            if example is None:
                example = {"prob": prob[0, 0].cpu().numpy(), "occ": occ[0, 0].cpu().numpy().astype(np.float32),
                           "input": gt_occupancy(record, t, grid, v)[0].numpy()}
    return {"scores": occupancy_scores(counts), "frames": frames, "example": example}
