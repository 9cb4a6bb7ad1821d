"""3D object detection inference: RGB-D views with known poses -> scored axis-aligned 3D boxes in `ref`.

The map is built exactly as `core.pipeline.map.map_frames` builds it (`ref` is `world_T_ref` when
given, else the camera of view 0; docs/conventions.md#frames), then the bundle's `detector` (core.models.detector3d)
scores its anchors, decodes boxes and suppresses overlaps. Boxes are canonical rows
(x, y, z, lx, ly, lz, yaw) in `ref` with yaw 0 (the paper's detector is axis-aligned).
Pass `world_T_cam = ref_T_cam` and `world_T_ref = identity` to give the views' poses in ref directly.
"""

from __future__ import annotations

import torch

from core.bundle import Bundle
from core.pipeline.map import map_frames

BOXES_FRAME = "ref"


def pad_detections(detections: list[dict[str, torch.Tensor]], *, device=None) -> dict[str, torch.Tensor]:
    """Per-item dict(boxes K_b×7, scores K_b) -> {"boxes": B×K×7, "scores": B×K, "valid": B×K bool},
    K = max K_b, zero-padded, each row best first."""
    B = len(detections)
    K = max((d["scores"].numel() for d in detections), default=0)
    if device is None:
        device = detections[0]["scores"].device if detections else "cpu"
    boxes = torch.zeros(B, K, 7, device=device)
    scores = torch.zeros(B, K, device=device)
    valid = torch.zeros(B, K, dtype=torch.bool, device=device)
    for b, d in enumerate(detections):
        k = d["scores"].numel()
        boxes[b, :k], scores[b, :k], valid[b, :k] = d["boxes"], d["scores"], True
    return {"boxes": boxes, "scores": scores, "valid": valid}


@torch.no_grad()
def detect(bundle: Bundle, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
           world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None = None, *, min_score: float = 0.0,
           nms_iou: float = 0.3, max_boxes: int = 50) -> dict[str, torch.Tensor]:
    """rgb: B×V×3×H×W in [0,1]; depth: B×V×H×W metres (0 = missing); pix_T_cam, world_T_cam: B×V×4×4;
    world_T_ref: B×4×4 or None (camera of view 0).

    Returns {"boxes": B×K×7 canonical in ref (yaw 0), "scores": B×K objectness in (0, 1), "valid": B×K}
    (zero-padded to the largest count; each item's boxes best first, scores ≥ min_score, after 3D NMS
    at `nms_iou`, at most `max_boxes`). `detections_per_item` turns it into a list of dicts.
    """
    detector = bundle.require("detector")
    features = map_frames(bundle, rgb, depth, pix_T_cam, world_T_cam, world_T_ref)["features"]  # B×F×Z×Y×X
    detections = detector.detect(features, min_score=min_score, nms_iou=nms_iou, max_boxes=max_boxes)
    return pad_detections(detections, device=features.device)


def detections_per_item(out: dict[str, torch.Tensor]) -> list[dict[str, torch.Tensor]]:
    """`detect`'s padded output -> list (per batch item) of dict(boxes K_b×7 in ref, scores K_b)."""
    return [{"boxes": out["boxes"][b, out["valid"][b]], "scores": out["scores"][b, out["valid"][b]]}
            for b in range(out["boxes"].shape[0])]
