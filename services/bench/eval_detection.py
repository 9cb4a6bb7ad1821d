"""Detection mAP of a detector bundle on the test set (the paper's §5.1 protocol on synthetic data).

Per test record, the map of time step 0 from all views (`core.pipeline.detect`), boxes in `ref`;
ground truth: the record's valid boxes of step 0 in `ref` with their centre in the grid, as their
axis-aligned bounding boxes — the detector is axis-aligned, and so is the paper's evaluation of it
(the same targets the detector trains on: core.tasks.detector.gt_boxes_ref + boxes_to_aabb).
AP is all-point interpolated over the whole test set at 3D IoU 0.33 / 0.5 / 0.75
(core.eval.average_precision.APAccumulator with core.eval.iou3d.iou_3d); one class, so mAP = AP.
"""

from __future__ import annotations

from typing import Iterable

import torch

from core.eval.average_precision import APAccumulator
from core.eval.iou3d import iou_3d
from core.models.detector_boxes import aabb_to_boxes, boxes_to_aabb
from core.pipeline.detect import detect, detections_per_item
from core.tasks.detector import gt_boxes_ref
from services.cli.eval_tasks.common import record_batch

IOU_THRESHOLDS = (0.33, 0.5, 0.75)


@torch.no_grad()
def evaluate_detection(bundle, records: Iterable[dict], *, device, t: int = 0) -> dict:
    """{"map": {"0.33": AP, "0.5": AP, "0.75": AP}, "frames", "gt_boxes", "detections"}."""
    grid = bundle.preset.grid
    acc = APAccumulator(iou_fn=iou_3d, thresholds=IOU_THRESHOLDS)
    frames = 0
    for record in records:
        batch = record_batch(record, device)
        out = detect(bundle, batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"],
                     batch["world_T_cam"][:, t], batch["world_T_ref"][:, t])
        pred = detections_per_item(out)[0]
        gt_batch = {"boxes": torch.as_tensor(record["boxes"])[None], "box_valid": torch.as_tensor(record["box_valid"])[None],
                    "world_T_ref": torch.as_tensor(record["world_T_ref"])[None]}
        boxes_ref, keep = gt_boxes_ref(gt_batch, t, grid)                        # 1×K×7, 1×K
        gt = aabb_to_boxes(boxes_to_aabb(boxes_ref[0, keep[0]]))                  # G×7, yaw 0
        acc.add_frame(pred["boxes"].cpu().numpy(), pred["scores"].cpu().numpy(), gt.numpy())
        frames += 1
    return {"map": {str(th): acc.ap(th) for th in IOU_THRESHOLDS}, "frames": frames,
            "gt_boxes": acc.num_gt, "detections": acc.num_detections}
