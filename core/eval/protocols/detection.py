"""The bundle's 3D detector on a dataset: AP over every (record, time step).

The detector (core.pipeline.detect) runs on the map of every time step of every record (all views,
known poses) and is scored against the record's boxes in ref_t — the valid ones whose centre lies
inside the grid, replaced by their axis-aligned bounding boxes (the paper's detector and its evaluation
are axis-aligned; the same ground truth the detector task trains on, core.tasks.detector.gt_boxes_ref).
All-point AP at 3D and BEV IoU (core.eval.method_ap), one class: the detector is class-agnostic.
"""

from __future__ import annotations

import numpy as np
import torch

from core.data.ground_truth import gt_occupancy
from core.eval.method_ap import MethodAP
from core.eval.protocols.inputs import record_batch
from core.models.detector_boxes import aabb_to_boxes, boxes_to_aabb
from core.pipeline.detect import detect, detections_per_item
from core.tasks.detector import gt_boxes_ref

NEEDS = ("mapper", "detector")
CLASS = "object"  # the detector is class-agnostic (one anchor class: car-sized objects)


def evaluate(bundle, records, *, device, thresholds, recorder=None) -> dict:
    """Detector AP over every (record, time step): {"ap": MethodAP, "frames", "example": (gt G×7, top-10
    detections D×7) of the first frame}. `recorder` (an eval recorder: `log_entry(**fields)`, as
    services.viz.rerun_eval.EvalRecorder) gets every (record, t): the observed occupancy, the ground-truth
    boxes scored against and the detections with their scores."""
    grid = bundle.preset.grid
    ap = MethodAP(thresholds)
    frames, example = 0, None
    for record_index, record in enumerate(records):
        batch = record_batch(record, device)
        batch.update({k: torch.as_tensor(np.asarray(record[k]))[None].to(device) for k in ("boxes", "box_valid")})
        batch["boxes"] = batch["boxes"].float()
        for t in range(batch["rgb"].shape[1]):
            out = detect(bundle, batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"],
                         batch["world_T_cam"][:, t], batch["world_T_ref"][:, t])
            pred = detections_per_item(out)[0]
            boxes_ref, keep = gt_boxes_ref(batch, t, grid)                     # 1×K×7, 1×K
            gt = aabb_to_boxes(boxes_to_aabb(boxes_ref[0, keep[0]]))          # G×7 axis-aligned, ref_t
            ap.add_frame(pred["boxes"].double().cpu().numpy(), pred["scores"].double().cpu().numpy(),
                         gt.double().cpu().numpy())
            frames += 1
            if recorder is not None:
                recorder.log_entry(record=record, record_index=record_index, t0=t,
                                   occupancy=gt_occupancy(record, t, grid)[0].numpy() > 0.5,
                                   boxes_true=gt.cpu().numpy(), boxes_pred=pred["boxes"].float().cpu().numpy(),
                                   scores_pred=pred["scores"].float().cpu().numpy())
            if example is None:
                example = (gt.cpu().numpy(), pred["boxes"][:10].cpu().numpy())
    return {"ap": ap, "frames": frames, "example": example}
