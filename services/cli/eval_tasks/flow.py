"""`n3dmap eval flow`: 3D imagination flow error in egomotion-stabilised scenes (the paper's protocol).

Each record contributes its consecutive pairs. Frame t+1 is registered into ref_t with the record poses
(so the numbers isolate the flow module from egomotion error, as the paper did). Rows: the model with
free voxels zeroed by the bundle's occupancy head (the paper's test-time rule; raw when there is none),
the model's raw flow, and the zero-motion baseline. L1 EPE over all voxels split full/static/moving;
EPE3D/Acc3DS/Acc3DR/outliers on the labelled occupied voxels of frame t (definitions:
core.eval.flow_metrics).
"""

from __future__ import annotations

import numpy as np
import torch

from core.data.ground_truth import gt_flow, gt_occupancy
from core.eval import flow_metrics as fm
from core.pipeline.flow import estimate_flow
from services.cli.eval import (add_eval_parser, add_rerun_option, check_rerun_option, iter_records,
                               load_bundle_for_eval, open_rerun_option, print_rerun_option, resolve_device)
from services.cli.eval_tasks.common import pair_inputs, record_batch
from services.cli.eval_tasks.plots import image_grid
from services.reports import Report
from services.viz.rerun_paths import PAIR

ROWS = ("model", "model_raw", "zero_motion")


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "flow", help="3D flow EPE (full/static/moving) vs the zero-motion baseline")
    parser.add_argument("--moving-threshold", type=float, default=1e-3,
                        help="ground-truth flow norm (voxels) above which a voxel counts as moving")
    add_rerun_option(parser)
    parser.set_defaults(func=run)


def evaluate(bundle, records, *, device, moving_threshold: float, recorder=None) -> dict:
    """Summed errors per row over every consecutive pair; `recorder` (services.viz.rerun_eval.EvalRecorder)
    gets every pair: the labelled occupied voxels, the true flow and the model's (occupancy-masked) flow."""
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
            preds = {"model": out["flow"], "model_raw": out["flow_raw"], "zero_motion": torch.zeros_like(gt)}
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
        from services.cli.main import CliError
        raise CliError("flow evaluation needs records with at least 2 time steps")
    return {"scores": {row: fm.flow_scores(s) for row, s in sums.items()}, "pairs": pairs, "example": example}


def _bev(flow: torch.Tensor) -> np.ndarray:
    """3×Z×Y×X -> Z×X largest flow magnitude along the vertical axis (voxels)."""
    return flow.norm(dim=0).amax(dim=1).numpy()


def run(args) -> int:
    from services.viz.rerun_eval import close_eval_recorder

    check_rerun_option(args)
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, ("mapper", "flow"), data_dir=args.data)
    recorder = open_rerun_option(args, bundle, timeline=PAIR, kind="flow")
    try:
        result = evaluate(bundle, iter_records(args.data, args.max_records), device=device,
                          moving_threshold=args.moving_threshold, recorder=recorder)
    finally:
        close_eval_recorder(recorder)
    scores = result["scores"]
    report = Report(kind="flow", title="3D imagination flow evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "pairs": result["pairs"],
                              "moving_threshold_voxels": args.moving_threshold, "device": str(device),
                              "occupancy_masking": "occupancy" in bundle.modules})
    report.metrics = {"flow": scores}
    report.text("Mean L1 endpoint error in voxels (Σ over x, y, z of |pred − gt|), egomotion-stabilised with "
                "the record poses; `moving` = voxels whose true flow exceeds the threshold.")
    report.table(["method", "full", "static", "moving"],
                 [[row, s["epe_l1_full"], s["epe_l1_static"], s["epe_l1_moving"]] for row, s in scores.items()])
    report.heading("Scene-flow scores on occupied voxels")
    report.text("EPE3D: mean L2 error (voxels). Acc3DS: EPE < 0.5 voxel or relative error < 5%. "
                "Acc3DR: EPE < 1 voxel or relative error < 10%. Outliers: EPE > 1.2 voxel or relative error "
                "> 10% (relative tests only where the true flow is non-zero).")
    report.table(["method", "EPE3D", "Acc3DS", "Acc3DR", "outliers"],
                 [[row, s["epe3d"], s["acc3ds"], s["acc3dr"], s["outliers"]] for row, s in scores.items()])
    z = scores["zero_motion"]
    report.text(f"Voxels: {z['voxels_full']} in all, {z['voxels_moving']} moving, {z['voxels_occupied']} occupied.")
    ex = result["example"]
    vmax = float(max(_bev(ex["gt"]).max(), 1e-6))
    report.figure("flow_bev", image_grid([("true |flow|", _bev(ex["gt"])), ("predicted |flow|", _bev(ex["pred"])),
                                          ("|error|", _bev(ex["pred"] - ex["gt"]))], vmin=0.0, vmax=vmax,
                                         suptitle="Bird's-eye view: max over height (voxels)"),
                  "Bird's-eye flow magnitude of the pair with the most moving voxels")
    out = report.write(args.out)
    m = scores["model"]
    print(f"flow: {result['pairs']} pairs, L1 EPE full {m['epe_l1_full']:.3f} static {m['epe_l1_static']:.3f} "
          f"moving {m['epe_l1_moving']:.3f} (zero-motion moving {z['epe_l1_moving']:.3f}) -> {out / 'report.md'}")
    print_rerun_option(args, recorder)
    return 0
