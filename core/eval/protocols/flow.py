"""3D imagination flow error in egomotion-stabilised scenes (the paper's protocol).

Each record contributes its consecutive pairs. Frame t+1 is registered into ref_t with the record poses
(so the numbers isolate the flow module from egomotion error, as the paper did). Rows: the model with
free voxels zeroed by the bundle's occupancy head (the paper's test-time rule; raw when there is none),
"model_filled": the same gate opened one voxel around moving occupied voxels (core.pipeline.flow_gate,
fill 1: the unseen inside of a moving object keeps its flow; raw when there is no occupancy head), the
model's raw flow, and the zero-motion baseline. L1 EPE over all voxels split full/static/moving;
EPE3D/Acc3DS/Acc3DR/outliers on the labelled occupied voxels of frame t (definitions:
core.eval.flow_metrics).
"""

from __future__ import annotations

import torch

from core.data.ground_truth import gt_flow, gt_occupancy
from core.errors import DataError
from core.eval import flow_metrics as fm
from core.eval.protocols.inputs import pair_inputs, record_batch
from core.pipeline.flow import estimate_flow
from core.pipeline.flow_gate import gate_flow

NEEDS = ("mapper", "flow")
ROWS = ("model", "model_filled", "model_raw", "zero_motion")
FILLED_GATE = 1  # voxels the "model_filled" row's gate opens around moving occupied voxels


def evaluate(bundle, records, *, device, moving_threshold: float, recorder=None) -> dict:
    """Errors per row over every consecutive pair: {"scores": {row: core.eval.flow_metrics.flow_scores},
    "pairs", "example": {"gt", "pred"} 3×Z×Y×X (voxels) of the pair with the most moving voxels}.
    `moving_threshold`: true flow norm (voxels) above which a voxel moves. `recorder` (an eval
    recorder: `log_entry(**fields)`, as services.viz.rerun_eval.EvalRecorder) gets every pair: the
    labelled occupied voxels, the true flow and the model's (occupancy-masked) flow."""
    grid = bundle.preset.grid
    sums = {row: {} for row in ROWS}
    example = None
    pairs = 0
    for record_index, record in enumerate(records):
        batch = record_batch(record, device)
        T = batch["rgb"].shape[1]
        for t in range(T - 1):
            out = estimate_flow(bundle, **pair_inputs(batch, t, t + 1))
            gt = gt_flow(record, t, grid)[None].to(device)  # 1×3×Z×Y×X
            occupied = gt_occupancy(record, t, grid)[None].to(device) > 0.5  # 1×1×Z×Y×X
            filled = out["flow_raw"] if "occupancy" not in out else gate_flow(
                out["flow_raw"], out["occupancy"], fill=FILLED_GATE)
            preds = {"model": out["flow"], "model_filled": filled, "model_raw": out["flow_raw"],
                     "zero_motion": torch.zeros_like(gt)}
            for row, pred in preds.items():
                sums[row] = fm.add_sums(sums[row], fm.flow_error_sums(
                    pred.float(), gt, occupied=occupied, moving_threshold=moving_threshold))
            pairs += 1
            if recorder is not None:
                recorder.log_entry(record=record, record_index=record_index, t0=t, t1=t + 1,
                                   occupancy=occupied[0, 0].cpu().numpy(), flow_true=gt[0].cpu().numpy(),
                                   flow_pred=out["flow"][0].float().cpu().numpy())
            if example is None or (gt.norm(dim=1) > moving_threshold).sum() > (example["gt"].norm(dim=0) > moving_threshold).sum():
                example = {"gt": gt[0].cpu(), "pred": out["flow"][0].float().cpu()}
    if pairs == 0:
        raise DataError("flow evaluation needs records with at least 2 time steps")
    return {"scores": {row: fm.flow_scores(s) for row, s in sums.items()}, "pairs": pairs, "example": example}
